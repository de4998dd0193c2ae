"""Influential views: a test of each view's leave-one-out effect on the projection (issue 39).

A view can be self-consistent (ordinary reprojection RMS) and still geometrically off: a frame of
a sweep with rolling-shutter shear or motion blur fits its own pose well and drags the lens. The
RMS rule (``VIEW_OUTLIER_FACTOR``) cannot see it; what it does is move the camera. So each view is
judged by how far leaving it out moves the projection over the covered region, against what the
solve's own uncertainty predicts for removing one view (a Cook's-distance / Hausman-style test):

- the view's linearised leave-one-out change of the intrinsics (the jackknife's influence function,
  ``uncertainty.jackknife_projection_rms``): ``dc_v = (S - S_v)^-1 h_v``;
- mapped to the pixels of the covered region (the cells at least ``ROBUST_COVER`` views observe),
  the camera rotation compensated (as every projection comparison here): ``dq_v = M dc_v``;
- if the model fits and every view is drawn from the same noise, ``dc_v`` has covariance
  ``sigma^2 [(S - S_v)^-1 - S^-1]`` (the difference of two efficient estimates' covariances). Views
  are not alike (blur, distance, how well the lens model fits where a view lies), so each view ``w``
  has its own residual variance ``s_w^2`` (its residuals over its points' dof less its pose's 6) and
  the covariance is the sandwich ``A (Q - s_v^2 S_v) A^T + s_v^2 S^-1 S_v S^-1`` with ``A = (S -
  S_v)^-1 - S^-1`` and ``Q = sum_w s_w^2 S_w`` (the formula above when all are equal). Without it
  the worst-fitting sweep of mrcal's fisheye set (frames 81-87, RMS 1.8x the median) was rejected.
  A view's variance counts up to the RMS rule's limit (``VIEW_OUTLIER_FACTOR`` x the median view's
  RMS): beyond it the excess is the view's defect and must not excuse its influence.
  ``T_v = dq_v^T (M C_v M^T)^+ dq_v`` is then chi-square with ``r`` degrees of freedom (the rank
  the covered region sees);
- only the parameter directions the solve resolves are tested. A model with more coefficients than
  the set determines (opencv8's rational terms on 13 views of OpenCV's right stereo set: three
  combinations with 1e-14 to 5e-11 of the best-determined one's information) has directions where the
  normal matrix is roundoff. It is accumulated in double precision (``J^T J``, then the Schur
  complement over the poses), each step an absolute error of a few ``eps`` times its largest terms
  (more where the pose terms cancel), so an eigenvalue ``mu`` of the scaled ``S`` (unit diagonal) has
  a relative error of at least ``eps / mu``. The test needs ``(S - S_v)^-1 - S^-1`` there: a view's
  share of ``mu`` over ``mu^2``, which inherits that error. Below ``mu = sqrt(eps)`` (1.5e-8) of the
  largest the relative error exceeds ``sqrt(eps)`` times the cancellation factor (which can be
  1e3-1e6), i.e. it is no longer small; such a direction's standard deviation is over 8000x the
  best-determined combination's: the data do not determine it, and neither its leave-one-out change
  nor that change's spread can be tested. So the change and its covariance are taken in the
  eigen-directions of the scaled ``S`` with at least ``RESOLVED_INFORMATION = sqrt(eps)`` of the
  largest eigenvalue, and ``(S - S_v)^-1 - S^-1`` is computed as ``(S - S_v)^-1 S_v S^-1`` (not as a
  difference of two large inverses). Counted, the unresolved directions made the statistic roundoff:
  right03 (a 0.023 px shift) scored 461 against 32, and a 1e-12 relative perturbation of the normal
  equations moved single views' statistics up to 100x (tests/calibration/test_view_influence.py);
- errors correlated within a view (a lens the model fits only approximately, a detector's bias
  along an edge) move the camera more than independent pixel noise of the same size: every
  ``T_v`` is scaled up alike. That
  common scale is a nuisance parameter, estimated robustly: ``lambda = max(1, median(T_v) /
  median(chi2_r))`` (a few bad views cannot move a median);
- a view is influential when ``T_v / lambda`` exceeds the chi-square quantile of a family-wise false
  alarm rate ``INFLUENCE_FALSE_ALARM`` over the set's views (Bonferroni: ``alpha / V`` each).

``calibrate(reject_views=True)`` removes the most influential view, re-solves, and tests again until
no view is significant, never removing a view without which an image corner or border side the set
covers would be uncovered (the verdict's coverage is kept; the test then stops, since the others'
significance may be that view's pull) and never going below ``MIN_VIEWS`` (the rejected views and
the reason are in the result's ``views`` and ``rejected_views``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from calibration.camera_model import CameraModel
from calibration.intrinsics.model import (
    BundleProblem,
    NormalEquations,
    camera_from_vector,
    information_scale,
    normal_equations_at,
)
from calibration.intrinsics.results import F64, MIN_VIEWS, VIEW_OUTLIER_FACTOR, ViewResult
from calibration.intrinsics.uncertainty import cell_point_means, coverage_counts, projection_jacobians
from calibration.intrinsics.views import ViewData, solve_views
from calibration.targets import Target
from calibration.verdict import uncovered_border, uncovered_corners

Solved = tuple[BundleProblem, F64, F64, F64, int]

INFLUENCE_FALSE_ALARM = 0.01
"""Family-wise false-alarm rate of the influence test over one set's views (1 %: a good set loses a
view to it once in a hundred calibrations)."""

ROBUST_COVER = 3
"""The test's region: image cells at least this many views observe (``robust_cells``)."""

PER_VIEW_VARIANCE = True
"""Each view's residual variance its own (a sandwich covariance of the leave-one-out change), not one for all."""

RESOLVED_INFORMATION = float(np.sqrt(np.finfo(np.float64).eps))
"""Directions of the (scaled) normal matrix with less than this share of the largest eigenvalue are not
resolved in double precision and are left out of the test (module docstring)."""

RANK_RCOND = 1e-6
"""Singular values of the whitened projection map below this share of the largest do not count (the
directions the rotation compensation takes out: numerically zero, not small)."""


@dataclass
class Influence:
    """The influence test of every view of one solve."""

    statistic: F64
    """(V,) ``T_v``: the leave-one-out projection change against its predicted covariance (chi-square units)."""
    dof: NDArray[np.int64]
    """(V,) ``r``: the rank the covered region sees of view v's change."""
    shift_px: F64
    """(V,) RMS length (px) of the leave-one-out projection change over the covered points."""
    predicted_px: F64
    """(V,) RMS length (px) of the change the solve's covariance predicts for leaving view v out
    (``sqrt(trace(M C_v M^T) / N)``, before the common scale)."""
    scale: float
    """``lambda``: the common scale of the statistic (>= 1)."""
    threshold: F64
    """(V,) the chi-square quantile each scaled statistic is tested against."""
    alpha: float

    @property
    def scaled(self) -> F64:
        return self.statistic / self.scale

    @property
    def significant(self) -> NDArray[np.bool_]:
        return self.scaled > self.threshold

    def reason(self, v: int) -> str:
        """Why view ``v`` is rejected, in words a user can act on."""
        return (f"influential view: leaving it out moves the projection over the covered region by "
                f"{self.shift_px[v]:.3f} px where the solve predicts "
                f"{self.predicted_px[v] * np.sqrt(self.scale):.3f} px for one view, {self.scaled[v]:.0f} in "
                f"chi-square units ({int(self.dof[v])} dof, "
                f"residual scale x{self.scale:.1f}) against {self.threshold[v]:.0f} at a {self.alpha:.0%} "
                f"false-alarm rate over the set's views; a self-consistent but geometrically wrong view "
                f"(motion blur, rolling shutter, a board moved during the exposure?)")


def view_influence(camera: CameraModel, nrm: NormalEquations, sigma2: float | F64, pts_px: F64, n_lens: int,
                   alpha: float = INFLUENCE_FALSE_ALARM) -> Influence:
    """The influence test (module docstring) of every view of a solve with normal equations ``nrm``
    (per-view blocks, ``normal_equations_at``) and residual variance ``sigma2``, over ``pts_px``
    (the covered region's points, px); ``n_lens`` of the solved parameters are the camera's (a board
    warp follows them and is marginalised)."""
    if nrm.Av is None or nrm.gcv is None:
        raise ValueError("the influence test needs the per-view normal-equation blocks (normal_equations_at)")
    V = nrm.D.shape[0]
    Dinv = np.linalg.inv(nrm.D)
    BDinv = nrm.B @ Dinv
    Sv = nrm.Av - np.einsum("vij,vkj->vik", BDinv, nrm.B)          # (V, nc, nc) each view's Schur share
    hv = nrm.gcv - np.einsum("vij,vj->vi", BDinv, nrm.gv)          # (V, nc) its reduced gradient
    S = Sv.sum(axis=0)
    s2 = np.broadcast_to(np.asarray(sigma2, dtype=np.float64), (V,))
    Q = np.einsum("v,vij->ij", s2, Sv)                             # the gradient's covariance (sandwich)
    Jc, Jw, valid = projection_jacobians(camera, pts_px)
    m = np.repeat(valid, 2)
    M = Jc[m]
    if Jw[m].shape[0] >= 6:
        M = M - Jw[m] @ (np.linalg.pinv(Jw[m]) @ Jc[m])              # rotation compensated
    n_pts = max(int(valid.sum()), 1)
    sc = information_scale(S)
    W = _resolved_directions(S, sc)
    S_inv = _inv_in(S, sc, W)
    T = np.zeros(V)
    r = np.zeros(V, dtype=np.int64)
    shift = np.zeros(V)
    pred = np.zeros(V)
    for v in range(V):
        Sr = S - Sv[v]
        Sr_inv = _inv_in(Sr, sc, W)
        dc = Sr_inv @ hv[v]
        SiSv = S_inv @ Sv[v]
        A = Sr_inv @ Sv[v] @ S_inv                                   # = Sr^-1 - S^-1, without the cancellation
        # covariance of the leave-one-out change: A (Q - s2_v S_v) A^T + s2_v S^-1 S_v S^-1
        # (= sigma^2 [(S - S_v)^-1 - S^-1] when every view has the same variance)
        C = A @ (Q - s2[v] * Sv[v]) @ A.T + s2[v] * SiSv @ S_inv
        C = 0.5 * (C + C.T)[:n_lens, :n_lens]
        dq = M @ dc[:n_lens]
        shift[v] = float(np.sqrt(np.sum(dq * dq) / n_pts))
        lam, U = np.linalg.eigh(C)
        L = U * np.sqrt(np.maximum(lam, 0.0))                        # C = L L^T
        Uq, s, _ = np.linalg.svd(M @ L, full_matrices=False)         # M C M^T = Uq s^2 Uq^T
        pred[v] = float(np.sqrt(np.sum(s * s) / n_pts))
        keep = s > RANK_RCOND * (s[0] if s.size else 0.0)
        if not np.any(keep):
            continue
        z = (Uq[:, keep].T @ dq) / s[keep]
        T[v] = float(z @ z)
        r[v] = int(keep.sum())
    ok = r > 0
    ratio = T[ok] / chi2.median(r[ok]) if np.any(ok) else np.ones(1)
    scale = max(1.0, float(np.median(ratio)))
    thr = np.where(ok, chi2.isf(alpha / max(V, 1), np.maximum(r, 1)), np.inf)
    return Influence(T, r, shift, pred, scale, thr, alpha)


def _resolved_directions(S: F64, sc: F64) -> F64:
    """Orthonormal basis (scaled parameters) of the directions the normal matrix ``S`` resolves:
    its scaled eigenvalues at least ``RESOLVED_INFORMATION`` of the largest (module docstring)."""
    Ss = S / sc[:, None] / sc[None, :]
    lam, U = np.linalg.eigh(0.5 * (Ss + Ss.T))
    return U[:, lam >= RESOLVED_INFORMATION * max(float(lam[-1]), 0.0)]


def _inv_in(S: F64, sc: F64, W: F64) -> F64:
    """``S``'s inverse restricted to the resolved directions ``W`` (scaled parameters), unscaled."""
    Ss = S / sc[:, None] / sc[None, :]
    Sw = W.T @ (0.5 * (Ss + Ss.T)) @ W
    return (W @ np.linalg.pinv(Sw, rcond=1e-14) @ W.T) / sc[:, None] / sc[None, :]


def reject_influential_views(model: str, size: tuple[int, int], views: list[ViewData], results: list[ViewResult],
                             target: Target, n_lens: int, solved: Solved,
                             alpha: float = INFLUENCE_FALSE_ALARM) -> tuple[list[ViewData], Solved, dict[str, Any]]:
    """Remove influential views one at a time (the most significant first), re-solving after each,
    until none is significant (module docstring). The most significant view is kept, and the test
    stops, when without it an image corner or border side would be uncovered (``calibration.verdict``)
    or fewer than ``MIN_VIEWS`` would be left (``kept_significant`` says which and why). The removed
    views' ``results`` say why; returns the kept views, their solve and the test's summary."""
    p, c, R, t, iters = solved
    nx = 16
    rejected: list[dict[str, Any]] = []
    kept: list[dict[str, Any]] = []
    inf = None
    for _ in range(len(views)):
        inf = _influence_of(p, c, R, t, views, size, n_lens, alpha)
        v = int(np.argmax(inf.scaled / inf.threshold))
        if not inf.significant[v]:
            break
        counts = np.array([coverage_counts(size, vd.uv, nx) for vd in views])
        total = counts.sum(axis=0)
        lost = sorted(_uncovered(total - counts[v]) - _uncovered(total))
        if lost or len(views) - 1 < MIN_VIEWS:
            # Kept, and the test stops: the others' significance may be this view's pull on them
            # (removing the next one instead made a render 0.62 -> 0.81 px worse).
            kept.append({**_row(inf, v, views[v].image),
                         "kept_because": (f"without it the {', '.join(lost)} would be uncovered; add views there"
                                          if lost else f"fewer than {MIN_VIEWS} views would be left")})
            break
        vd = views[v]
        vr = results[vd.index]
        vr.reason, vr.outlier = inf.reason(v), True
        rejected.append(_row(inf, v, vd.image))
        keep = [k for k in range(len(views)) if k != v]
        views = [views[k] for k in keep]
        p, c, R, t, it = solve_views(model, size, views, target, start=(c, R[keep], t[keep]),
                                     regularise=p.prior_w is not None)
        iters += it
    summary: dict[str, Any] = {
        "rule": "a view is rejected when leaving it out moves the projection over the covered region more than "
                "the solve's own uncertainty predicts for removing one view (chi-square test, common residual "
                "scale from the median view, Bonferroni over the views); the most influential first, re-solved "
                "after each; the most influential view is kept, and the test stops, when without it an image "
                "corner or border side the set covered would be uncovered",
        "false_alarm": alpha, "rejected": rejected,
        "scale": None if inf is None else round(inf.scale, 3),
        "kept_significant": kept,
    }
    return views, (p, c, R, t, iters), summary


def _row(inf: Influence, v: int, image: str) -> dict[str, Any]:
    return {"image": image, "shift_px": round(float(inf.shift_px[v]), 4),
            "predicted_px": round(float(inf.predicted_px[v] * np.sqrt(inf.scale)), 4),
            "statistic": round(float(inf.scaled[v]), 2), "threshold": round(float(inf.threshold[v]), 2),
            "dof": int(inf.dof[v])}


def _uncovered(coverage: NDArray[np.int64]) -> set[str]:
    """The image corners and border sides the verdict would call uncovered (``calibration.verdict``)."""
    return set(uncovered_corners(coverage)) | {f"border {k}" for k in uncovered_border(coverage)}


def _influence_of(p: BundleProblem, c: F64, R: F64, t: F64, views: list[ViewData], size: tuple[int, int],
                  n_lens: int, alpha: float) -> Influence:
    free = np.ones(len(c), dtype=bool)
    nrm, r = normal_equations_at(p, c, R, t, free)
    kept = np.repeat(p.weights() > 0, 2)
    if PER_VIEW_VARIANCE:
        # each view's own residual variance (its pose's 6 dof taken off): a blurred or distant view,
        # or one the lens model fits less well, is expected to move the camera more
        e = np.add.reduceat(r * r, 2 * p.starts[:-1])
        m = np.add.reduceat(kept.astype(np.float64), 2 * p.starts[:-1])
        s2 = e / np.maximum(m - 6.0, 1.0)
        # up to the RMS rule's limit (VIEW_OUTLIER_FACTOR x the median view's RMS): beyond it the
        # excess is the view's own defect, which must not excuse its influence (a render's view
        # sheared 4 px and blurred, RMS 6.6x the median, went undetected without the cap)
        sigma2: float | F64 = np.minimum(s2, VIEW_OUTLIER_FACTOR**2 * float(np.median(s2)))
    else:
        sigma2 = float(np.sum(r * r)) / max(int(kept.sum()) - len(c) - 6 * p.n_views, 1)
    camera = camera_from_vector(p.model, size, c[:n_lens])
    pts = robust_cells(size, views)
    return view_influence(camera, nrm, sigma2, pts, n_lens, alpha)


def robust_cells(size: tuple[int, int], views: list[ViewData], nx: int = 16, need: int = ROBUST_COVER) -> F64:
    """Mean point (px) of each image cell that at least ``need`` views observe (fewer: all covered
    cells): the region the solve determines without any one view. Outside it, leaving out the one
    view that covered a cell extrapolates there, which is what removing it predicts, not a fault."""
    uv = np.vstack([v.uv for v in views])
    n_cover = np.sum([coverage_counts(size, v.uv, nx).reshape(-1) > 0 for v in views], axis=0)
    counts = coverage_counts(size, uv, nx).reshape(-1)
    means = np.full((len(counts), 2), np.nan)
    means[counts > 0] = cell_point_means(size, uv, nx)
    ok = n_cover >= need
    if ok.sum() < 4:
        ok = counts > 0
    return means[ok]

