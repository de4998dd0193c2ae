"""Camera intrinsics from views of a planar target, with honest uncertainty.

Pipeline (every model — ``opencv5``, ``opencv8``, ``division`` — goes through the same solver):

1. **Closed-form start (Zhang).** ``cv2.initCameraMatrix2D`` (Zhang's homography constraints with
   the principal point at the image centre) gives ``K``; ``cv2.solvePnP`` (IPPE) gives each view's
   pose with that ``K`` and no distortion.
2. **Our own bundle refinement.** A Levenberg-Marquardt over all intrinsics and every view's pose,
   minimising pixel reprojection error. It exploits the problem's arrow structure (intrinsics
   couple to everything, each pose only to its own view) with a Schur complement, so a 186-view
   set costs a few 12x12 solves per iteration. This is our own code, not ``scipy.optimize
   .least_squares``: scipy's dense solvers are O(m n^2) in the poses and its sparse solver (LSMR)
   is inexact on the ill-conditioned rational model, and we need the exact normal matrix at the
   optimum for the covariance anyway. It runs in two stages (first radial term only, then the
   full model) so a strongly distorted lens does not start far from its basin.
   For ``circle_plate`` detections that carry the raw ellipse centres (``uv_ellipse``) the
   perspective bias of each mark (``calibration.detect.conic.circle_centre_bias_px``) is recomputed from
   the current camera and poses and the solve repeated until the bias changes by < 1e-4 px
   (two or three rounds): the bias correction lives inside the estimation loop.
3. **Outliers** (rule): a point is an outlier when its residual length exceeds
   ``5 * sigma_r``, with ``sigma_r = 1.4826 * median(|residual component|)`` over the kept points
   (a robust per-axis standard deviation, residuals weighted by the points' precision); a view is
   an outlier when its RMS exceeds ``3 *`` the median view RMS. Where the points' stated
   precision explains the residuals, outlier points are weighted out (weight 0, reported per view
   as ``n_outlier_points``) and the solve repeated (``views.reject_outlier_points``); elsewhere,
   and for views, they are flagged, and with ``drop_outliers=True`` they (and the
   outlier points) are removed and the solve repeated once.
   **Weights**: each point is weighted by its view's detection precision (``Detection
   .uv_sigma_px``, ``calibration.observations.point_weights``) with the error that the stated
   precision does not explain added first (``systematic_floor_px``, estimated from the
   residuals): where a lens or board does not fit to the detector's precision the weights come
   back to nearly uniform.
4. **Covariance**: ``sigma^2 (J^T J)^-1`` at the optimum with ``sigma^2 = sum(r^2) / (m - n)``;
   the intrinsics block is the inverse of the Schur complement, i.e. marginalised over the poses.
   That formula assumes independent pixel noise. Real detectors (and our rendered benchmark)
   make errors that are correlated within a view, which it cannot see; so a grouped view-level
   jackknife (up to 10 groups; linearised: each replicate is one Gauss-Newton step from the
   optimum with its group's normal-equation blocks removed, ``uncertainty
   .jackknife_projection_rms``) estimates the projection uncertainty empirically too, on the
   cells at least 3 views saw (elsewhere a replicate
   without the one view that covered a cell extrapolates, which over-reported small targets),
   and when it is *significantly* larger than the analytic value on the same cells (beyond the
   jackknife's own sampling noise, ``1 + 2 / sqrt(2 (G - 1))``) the analytic covariance is scaled
   up to match (``uncertainty.inflation``; both estimates are reported). Residuals are weighted
   by each point's own detection uncertainty (``Detection.uv_sigma_px``); ``sigma^2`` is then the
   scale of a point of weight 1.
5. **Projection uncertainty** (mrcal's idea, docs/cli.md ``uncertainty.projection_rms_px``):
   rays through a grid of pixels are projected with perturbed intrinsics; a small rotation of the
   camera frame cannot be told from some intrinsics changes (principal point vs. pan/tilt), so the
   best rotation (fitted over the covered region) is compensated. The 2x2 covariance of each grid
   pixel's compensated projection follows linearly from the intrinsics covariance; its RMS over
   the covered grid cells is ``projection_rms_px``. Projection does not depend on the distance
   along a ray, so the working distance drops out (unlike mrcal, whose reference frame moves with
   the poses; marginalising over the poses and compensating the rotation plays that role here).

Modules: ``results`` (result types, limits, the error), ``model`` (the vectorised model and the
bundle solver), ``views`` (collecting views, the start, the solve loop, outliers), ``uncertainty``
(projection uncertainty, jackknife, comparing cameras), ``kernels`` (the compiled projection with
analytic derivatives, numba), ``schur_kernels`` (the compiled Schur step), ``solver`` (``calibrate``),
``crossval`` (k-fold cross-validation), ``selection`` (choosing the model and the board warp by it:
``select_by_cross_validation``). Planned views and synthetic detections with truth are
``calibration.synthetic``. Everything public is exported here: ``from calibration.intrinsics import X``
is the interface.
"""

from calibration.geometry import exp_so3 as rotations
from calibration.intrinsics.crossval import (
    CV_MIN_REPEATS,
    CV_REPEATS,
    SELECT_MARGIN,
    cross_validate,
    fold_partitions,
    median_half_width,
)
from calibration.intrinsics.model import (
    camera_from_vector,
    intrinsic_steps,
    intrinsics_vector,
    param_names,
    project_normalized,
)
from calibration.intrinsics.results import (
    JACKKNIFE_GROUPS,
    JACKKNIFE_MIN_VIEWS,
    MIN_POINTS_PER_VIEW,
    MIN_VIEWS,
    POINT_OUTLIER_SIGMAS,
    VIEW_OUTLIER_FACTOR,
    CrossValidationError,
    IntrinsicsError,
    IntrinsicsResult,
    ViewResult,
)
from calibration.intrinsics.selection import select_by_cross_validation
from calibration.intrinsics.solver import calibrate
from calibration.intrinsics.uncertainty import (
    cell_grid,
    cell_point_means,
    coverage_counts,
    covered_point_means,
    covered_points,
    projection_difference,
    projection_jacobians,
    projection_uncertainty,
    uncertainty_summary,
)

__all__ = [
    "JACKKNIFE_GROUPS", "JACKKNIFE_MIN_VIEWS", "MIN_POINTS_PER_VIEW", "MIN_VIEWS", "POINT_OUTLIER_SIGMAS",
    "VIEW_OUTLIER_FACTOR", "IntrinsicsError", "CrossValidationError", "IntrinsicsResult", "ViewResult", "calibrate",
    "camera_from_vector", "cell_grid", "cell_point_means", "coverage_counts", "covered_point_means",
    "covered_points", "cross_validate", "select_by_cross_validation", "SELECT_MARGIN", "CV_REPEATS",
    "CV_MIN_REPEATS", "fold_partitions", "median_half_width",
    "intrinsic_steps", "intrinsics_vector", "param_names", "project_normalized", "projection_difference",
    "projection_jacobians", "projection_uncertainty", "rotations",
    "uncertainty_summary",
]
