"""Calibrating the splined stereographic model (``calibration.splined``) from views of a planar target.

1. **Start**: the ``fisheye4`` calibration of the same views (``calibrate``) gives the focal
   lengths, the principal point and every view's pose; the spline's control values are then the
   regularised linear least-squares fit of what fisheye4 projects at the observed points.
2. **Grid** (unless given): the interior spans the observed points' field under the start
   camera (5 % margin; mrcal spans the whole imager, but knots where no point falls are set by the
   regulariser alone); the columns are the most of ``GRID_COLUMNS`` the data carry (at least
   ``MIN_OBS_PER_PARAM`` observed coordinates per parameter in *half* the data: a grid that a
   cross-validation fold cannot carry cannot be validated); rows follow from the image's
   vertical field at the same knot spacing.
3. **Solve** (``splined_problem``): Levenberg-Marquardt over the control values and every pose
   (left rotation increment, then translation); the core ``fx, fy, cx, cy`` stays at the start's (a
   gauge: the spline absorbs it), with an analytic sparse Jacobian. Points are weighted by their detection
   precision (``ViewData.weights``, relative; none stated: all 1). Outlier points (> ``POINT_OUTLIER_SIGMAS``
   robust sigma) are weighted out once and the solve repeated where the detectors' stated precision
   explains the residual scale (the parametric solver's rule); otherwise they are only flagged.
4. **Regularisation** (``splined_problem``, so that control points the data barely see do not fold the
   map): every control value is pulled towards the spline that reproduces the start (fisheye4) lens,
   each weighing as one observation at ``PRIOR_PX`` pixels off, and a weak curvature term keeps the
   map smooth.
5. **Uncertainty**: the sandwich covariance ``sigma^2 H^-1 (J_o^T J_o) H^-1`` (``H`` with the
   regularisation, ``J_o`` the observations only, as mrcal; the prior's own uncertainty is not in
   it), marginalised over the poses; projection uncertainty as for every model (``uncertainty_summary``). No jackknife.

Refusal: a splined model needs many views spread over the image (``MIN_VIEWS_SPLINED``) and
``MIN_OBS_PER_PARAM`` observations per parameter at the coarsest grid; with fewer (13-31 views of a
small board) mrcal's splined model folds (5-11 px split-half), and ``calibrate`` raises
IntrinsicsError saying so (cross-validation then refuses the candidate with that reason).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Final

import numpy as np

from calibration import splined
from calibration.camera_model import CameraModel
from calibration.geometry import make_transform
from calibration.intrinsics.results import (
    F64,
    MIN_VIEWS,
    IntrinsicsError,
    IntrinsicsResult,
)
from calibration.intrinsics.splined_problem import _Problem
from calibration.intrinsics.uncertainty import coverage_counts, uncertainty_summary
from calibration.intrinsics.views import ViewData, collect_views, outlier_points, warp_basis
from calibration.observations import Detection
from calibration.targets import Target
from calibration.verdict import assess

MIN_VIEWS_SPLINED: Final = 40
"""Fewer views do not carry a splined model (mrcal's folds at 13-31 views; its fisheye set has 186)."""
MIN_OBS_PER_PARAM: Final = 20
"""Observed coordinates per parameter (spline and core) the chosen grid must have."""
GRID_COLUMNS: Final = (30, 24, 20, 16, 12, 10, 8)


def calibrate_splined(detections: Sequence[Detection], target: Target, *,
                      image_size: tuple[int, int] | None = None,
                      layout: splined.SplineLayout | None = None, check: bool = True,
                      max_iter: int = 60, board_warp: bool = False,
                      point_weights: Sequence[F64] | None = None) -> IntrinsicsResult:
    """Calibrate the splined stereographic model (module docstring). ``layout``: a fixed grid
    (default: chosen from the data); ``check=False`` skips the refusal rules (for experiments);
    ``board_warp``: also solve the target's two warp heights (mrcal's parabolic warp, as
    ``calibrate(board_warp=True)``; the start is then the warped fisheye4 solve);
    ``point_weights``: one relative weight per point of each detection (e.g. mrcal's ``2^-level`` of
    its detector's pyramid level), instead of the weights from the detections' stated precision.
    Raises IntrinsicsError when the data cannot carry the model."""
    from calibration.intrinsics.solver import calibrate

    t0 = time.perf_counter()
    views, results, size = collect_views(detections, target, image_size)
    if len(views) < MIN_VIEWS:
        raise IntrinsicsError(f"only {len(views)} usable view(s) of the target; need at least {MIN_VIEWS}")
    if check and len(views) < MIN_VIEWS_SPLINED:
        raise IntrinsicsError(f"the splined model needs at least {MIN_VIEWS_SPLINED} views spread over the "
                              f"whole image, got {len(views)}: its control points would be set by the "
                              "regulariser, not the data (it folds); use fisheye4 or opencv8, or take more views")
    start = calibrate(detections, target, "fisheye4", image_size=size, jackknife=False, board_warp=board_warp)
    cam0 = start.camera
    R = np.array([start.views[v.index].T_cam_target[:3, :3] for v in views])  # type: ignore[index]
    t = np.array([start.views[v.index].T_cam_target[:3, 3] for v in views])   # type: ignore[index]
    n_pts = sum(len(v.X) for v in views)
    X = np.vstack([v.X for v in views])
    view = np.concatenate([np.full(len(v.X), k) for k, v in enumerate(views)])
    P = np.einsum("nij,nj->ni", R[view], X) + t[view]
    if layout is None:
        layout = _choose_layout(splined.stereographic(P)[0], 2 * n_pts, check)
    elif check and 2 * n_pts < MIN_OBS_PER_PARAM * (4 + 2 * layout.n_ctrl):
        raise IntrinsicsError(f"a {layout.nx}x{layout.ny} splined grid has {2 * layout.n_ctrl} parameters; "
                              f"{n_pts} points carry at most {n_pts // MIN_OBS_PER_PARAM}")
    obs = np.vstack([v.uv for v in views])
    core = np.array([cam0.fx, cam0.fy, cam0.cx, cam0.cy])
    prob = _Problem(layout, X, obs, view, len(views), warp_basis(target, X) if board_warp else None)
    if board_warp and start.board_warp is not None:
        prob.wp = np.asarray(start.board_warp["height_mm"], dtype=np.float64) / 1000.0
    prob.sigma_px = max(float(start.sigma_px), 1e-3)
    ctrl = prob.initial_ctrl(core, cam0)
    x = np.concatenate([core, ctrl])
    w0 = np.concatenate([v.weights() for v in views])       # the detector's relative precision
    if point_weights is not None:
        given = [np.asarray(point_weights[v.index], dtype=np.float64).reshape(-1) for v in views]
        if any(len(g) != len(v.X) for g, v in zip(given, views, strict=True)):
            raise IntrinsicsError("point_weights: give one weight per point of each detection")
        w0 = np.concatenate(given)
    w = w0.copy()
    x, R, t, iters = prob.solve(x, R, t, w, max_iter)
    # on mrcal's fisheye corners (no stated precision) the 5-sigma points were 0.4 % of the corners within
    # 1000 px of the centre and 23 % beyond 3000 px: dropping them left them 1.94 px off (mrcal: 1.46)
    out, detection_failures = outlier_points(prob.obs_residuals(x, R, t).reshape(-1, 2) * w0[:, None], w0 > 0, views)
    if detection_failures and np.any(out & (w0 > 0)):
        w = np.where(out, 0.0, w0)
        x, R, t, it2 = prob.solve(x, R, t, w, max_iter)
        iters += it2
    return _result(prob, x, R, t, w, views, results, size, start.param_names, iters, time.perf_counter() - t0,
                   flagged=out)


def _choose_layout(u: F64, n_obs: int, check: bool) -> splined.SplineLayout:
    """The grid whose interior spans the observed stereographic points ``u`` (5 % margin; beyond
    them the edge segments extrapolate, as anywhere without data) with the most columns the data
    carry in half the set."""
    ux = 1.05 * float(np.max(np.abs(u[:, 0])))
    uy = 1.05 * float(np.max(np.abs(u[:, 1])))
    theta = 2.0 * np.arctan(ux / 2.0)
    for nx in GRID_COLUMNS:
        lay = splined.layout_for_field(theta, uy, nx)
        if n_obs // 2 >= MIN_OBS_PER_PARAM * (4 + 2 * lay.n_ctrl):
            return lay
    lay = splined.layout_for_field(theta, uy, GRID_COLUMNS[-1])
    if check:
        raise IntrinsicsError(f"too few points for the splined model: {n_obs // 2} points carry no grid "
                              f"(the coarsest, {lay.nx}x{lay.ny}, needs {MIN_OBS_PER_PARAM * (4 + 2 * lay.n_ctrl)}); "
                              "use fisheye4 or opencv8")
    return lay


def _result(prob: _Problem, x: F64, R: F64, t: F64, w: F64, views: list[ViewData], results: list, size: tuple[int, int],
            core_names: list[str], iters: int, time_s: float, flagged: np.ndarray | None = None) -> IntrinsicsResult:
    lay = prob.lay
    H, _, Jo, _ = prob.normal(x, R, t, w)
    ro = prob.obs_residuals(x, R, t).reshape(-1, 2)
    kept = w > 0
    n_kept = 2 * int(kept.sum())
    dof = max(n_kept - prob.n_intr - prob.nw - 6 * prob.V, 1)
    sigma2 = float(np.sum((ro[kept] * w[kept, None]) ** 2)) / dof   # a point of weight 1
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hinv = np.linalg.pinv(H / d[:, None] / d[None, :], hermitian=True) / d[:, None] / d[None, :]
    B = Hinv[:prob.n_intr - 4]
    cov_s = sigma2 * B @ (Jo.T @ (Jo @ B.T))                       # sandwich, marginal over the poses
    warp = None
    if prob.nw:
        Bw = Hinv[-prob.nw:]
        sw = np.sqrt(np.maximum(np.diag(sigma2 * Bw @ (Jo.T @ (Jo @ Bw.T))), 0.0))
        warp = {"height_mm": [round(float(v) * 1000.0, 4) for v in prob.wp],
                "sigma_mm": [round(float(v) * 1000.0, 4) for v in sw],
                "model": "z += w0 * 4 xr (1 - xr) + w1 * 4 yr (1 - yr), xr, yr in [0, 1] across the target"}
    cov_i = np.zeros((prob.n_intr, prob.n_intr))                   # the held core: no variance of its own
    cov_i[4:, 4:] = cov_s
    # the camera's parameter vector: fx fy cx cy, the grid's header (fixed: zero variance), control values
    nh = splined.HEADER
    n_all = 4 + nh + 2 * lay.n_ctrl
    keep = np.r_[0:4, 4 + nh:n_all]
    cov = np.zeros((n_all, n_all))
    cov[np.ix_(keep, keep)] = cov_i
    K = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
    camera = CameraModel("splined", size[0], size[1], K, np.concatenate([lay.header(), x[4:prob.n_intr]]))
    starts = np.concatenate([[0], np.cumsum([len(v.X) for v in views])])
    for k, v in enumerate(views):
        vr = results[v.index]
        e = ro[starts[k]:starts[k + 1]]
        vr.used = True
        vr.n_points = len(v.X)
        vr.rms_px = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        vr.T_cam_target = make_transform(R[k], t[k])
        vr.ids, vr.uv, vr.residuals_px = v.ids, v.uv, e
        flag = ~kept if flagged is None else (~kept | flagged)
        vr.n_outlier_points = int(flag[starts[k]:starts[k + 1]].sum())
        if v.sigma is not None and len(v.sigma):
            vr.corner_sigma_px = float(np.median(v.sigma))
    rms = float(np.sqrt(np.mean(np.sum(ro[kept] ** 2, axis=1))))
    points_uv = np.vstack([v.uv for v in views])
    coverage = coverage_counts(size, points_uv)
    unc, umap = uncertainty_summary(camera, cov, coverage, points_uv)
    unc["projection_rms_analytic_px"] = unc["projection_rms_px"]
    unc["inflation"] = 1.0
    names = ["fx", "fy", "cx", "cy", "Nx", "Ny", "fov_x_deg"] + [
        f"{a}_{j}_{i}" for a in ("dx", "dy") for j in range(lay.ny) for i in range(lay.nx)]
    verdict = assess(n_views=len(views), size=size, coverage=coverage, normals=R[:, :, 2], sigmas={},
                     values={n: float(v) for n, v in zip(core_names[:4], x[:4], strict=True)}, uncertainty=unc,
                     n_outlier_views=0, model="splined")
    return IntrinsicsResult(camera=camera, rms_px=rms, sigma_px=float(np.sqrt(sigma2 / 2)), views=results,
                            param_names=names, covariance=cov, uncertainty=unc, verdict=verdict,
                            coverage=coverage, uncertainty_map_px=umap, iterations=iters, time_s=time_s,
                            board_warp=warp)
