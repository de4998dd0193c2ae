"""Views for the solver: collecting detections, the closed-form start, the solve loop with the circle bias, outliers."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import N_DIST
from calibration.detect import circle_centre_bias_px
from calibration.geometry import exp_so3, make_transform
from calibration.intrinsics.model import (
    BundleProblem,
    camera_from_vector,
    levenberg_marquardt,
    regularisation,
)
from calibration.intrinsics.results import (
    F64,
    MIN_POINTS_PER_VIEW,
    POINT_OUTLIER_SIGMAS,
    VIEW_OUTLIER_FACTOR,
    IntrinsicsError,
    ViewResult,
)
from calibration.observations import Detection, effective_sigmas, point_weights
from calibration.targets import CirclePlate, Points3D, Target

# --------------------------------------------------------------------------------------------
# set-up


@dataclass
class ViewData:
    index: int
    image: str
    ids: NDArray[np.int64]
    X: F64
    uv: F64
    ellipse: bool
    w: F64 | None = None
    """(n,) relative weights of the points from their detection uncertainty, or None (all 1)."""
    sigma: F64 | None = None
    """(n,) the points' own detection uncertainty (px, ``Detection.uv_sigma_px``), or None."""
    rejected: NDArray[np.bool_] | None = None
    """(n,) points weighted out as outliers (> ``POINT_OUTLIER_SIGMAS`` robust sigma), or None."""

    def weights(self) -> F64:
        """The points' weights in the solve: detection weights, 0 for rejected points."""
        w = np.ones(len(self.X)) if self.w is None else self.w
        return w if self.rejected is None else np.where(self.rejected, 0.0, w)


def collect_views(detections: Sequence[Detection], target: Target,
             image_size: tuple[int, int] | None) -> tuple[list[ViewData], list[ViewResult], tuple[int, int]]:
    if isinstance(target, Points3D):
        raise IntrinsicsError("calib intrinsics needs a planar target (chessboard, charuco, circle_plate, "
                               "circle_grid); for a 3D target use calib dlt")
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    found = [d for d in detections if d.found]
    if detections and not found:
        reasons = sorted({d.reason for d in detections if d.reason})
        raise IntrinsicsError(
            f"the target ({target.describe()}) was found in none of the {len(detections)} images"
            + (f" ({reasons[0]})" if reasons else "")
            + "; is the target file the one in the images (type, size, rows and columns)?")
    sizes = [d.image_size for d in found if d.image_size != (0, 0)]
    if image_size is None:
        if not sizes:
            raise IntrinsicsError("image size unknown: no detection carries it; pass image_size")
        # The most common size wins; views of another size are reported as not used.
        image_size = max(set(sizes), key=sizes.count)
    views: list[ViewData] = []
    results: list[ViewResult] = []
    for k, d in enumerate(detections):
        vr = ViewResult(image=d.image, used=False)
        results.append(vr)
        if not d.found:
            vr.reason = d.reason or "target not found"
            continue
        if d.image_size not in ((0, 0), image_size):
            vr.reason = (f"image size {d.image_size[0]}x{d.image_size[1]} differs from the calibration's "
                         f"{image_size[0]}x{image_size[1]} (the most common size); one calibration per "
                         "camera and resolution")
            continue
        ids = np.asarray(d.ids, dtype=np.int64).reshape(-1)
        bad = [int(i) for i in ids if int(i) not in where]
        if bad:
            raise IntrinsicsError(f"{d.image}: point ids {bad[:5]} do not exist on the target "
                                   f"({target.describe()}); wrong target file?")
        use_ell = isinstance(target, CirclePlate) and d.uv_ellipse is not None
        uv = np.asarray(d.uv_ellipse if use_ell else d.uv, dtype=np.float64).reshape(-1, 2)
        ok = np.all(np.isfinite(uv), axis=1)
        if ok.sum() < MIN_POINTS_PER_VIEW:
            vr.reason = f"only {int(ok.sum())} points (need {MIN_POINTS_PER_VIEW})"
            continue
        X = tp.xyz_m[[where[int(i)] for i in ids[ok]]]
        sig = None if d.uv_sigma_px is None else np.asarray(d.uv_sigma_px, dtype=np.float64)[ok]
        views.append(ViewData(k, d.image, ids[ok], X, uv[ok], use_ell, sigma=sig))
        vr.n_points = int(ok.sum())
    set_weights(views)
    return views, results, image_size


def set_weights(views: list[ViewData], floor_px: float | None = None) -> None:
    """Weight each view's points by their detection uncertainty (``point_weights``), with the
    error no local fit sees taken as ``floor_px`` (default: ``point_weights``' own floor)."""
    sigmas = [v.sigma for v in views]
    for v, w in zip(views, point_weights(sigmas, [len(v.X) for v in views], floor_px=floor_px), strict=True):
        v.w = w


def weighting_sigmas(views: list[ViewData]) -> F64 | None:
    """(M,) every point's uncertainty as the weights use it (``effective_sigmas``), or None when
    some view has none."""
    eff, _ = effective_sigmas([v.sigma for v in views], [len(v.X) for v in views])
    if any(e is None for e in eff):
        return None
    return np.concatenate([e for e in eff if e is not None])


def initial_estimate(views: list[ViewData], size: tuple[int, int]) -> tuple[F64, F64, F64]:
    """Zhang's closed form for K (principal point at the centre), then IPPE poses."""
    obj = [v.X.astype(np.float32) for v in views]
    img = [v.uv.astype(np.float32) for v in views]
    try:
        K = cv2.initCameraMatrix2D(obj, img, size, 1.0)
    except cv2.error as exc:
        raise IntrinsicsError(f"closed-form initialisation failed ({exc.err}); are the views degenerate "
                               "(all parallel to each other)?") from exc
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise IntrinsicsError("closed-form initialisation failed: the views do not determine a focal "
                               "length (all views parallel? tilt the target between views)")
    # initCameraMatrix2D forces fx == fy from the mean; a wild value means degenerate views.
    R = np.empty((len(views), 3, 3))
    t = np.empty((len(views), 3))
    for k, v in enumerate(views):
        ok, rv, tv = cv2.solvePnP(v.X, v.uv, K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rv, tv = cv2.solvePnP(v.X, v.uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise IntrinsicsError(f"{v.image}: no initial pose (points degenerate?)")
        R[k] = exp_so3(rv.ravel())
        t[k] = tv.ravel()
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), R, t


def warp_basis(target: Target, X: F64) -> F64:
    """(M, 2) board-warp basis of target points ``X`` (metres): ``4 xr (1 - xr)`` and ``4 yr (1 - yr)``
    with ``xr``, ``yr`` the point's position across the target's extent of points, 0 to 1 (mrcal's
    parabolic warp; 1 at the centre line, 0 at the outer points)."""
    P = target.points().xyz_m
    lo, hi = P[:, :2].min(axis=0), P[:, :2].max(axis=0)
    r = (np.asarray(X, dtype=np.float64)[:, :2] - lo) / np.maximum(hi - lo, 1e-12)
    return 4.0 * r * (1.0 - r)


def build_problem(model: str, size: tuple[int, int], views: list[ViewData], warp_target: Target | None = None,
                  regularise: bool = False) -> BundleProblem:
    """The bundle problem of ``views``; with ``warp_target`` its points carry the board-warp basis
    (``kernels``: the parameter vector then has the two warp entries after the lens's); ``regularise``:
    with mrcal's regularisation (``model.regularisation``, weighed by the kept points' count)."""
    counts = np.array([len(v.X) for v in views])
    w = np.concatenate([v.weights() for v in views])
    X = np.vstack([v.X for v in views])
    if warp_target is not None:
        X = np.ascontiguousarray(np.column_stack([X, warp_basis(warp_target, X)]))
    p = BundleProblem(model, size, X, np.vstack([v.uv for v in views]),
                      np.repeat(np.arange(len(views)), counts).astype(np.int64),
                      np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), w)
    if regularise:
        p.prior_w, p.prior_at = regularisation(model, size, 2 * int(np.sum(w > 0)))
    return p


def circle_bias(p: BundleProblem, views: list[ViewData], c: F64, R: F64, t: F64, radius_m: float) -> F64:
    cam = camera_from_vector(p.model, p.size, c[:4 + N_DIST[p.model]])
    out = np.zeros_like(p.obs)
    for k, v in enumerate(views):
        if v.ellipse:
            sl = slice(p.starts[k], p.starts[k + 1])
            out[sl] = circle_centre_bias_px(cam, make_transform(R[k], t[k]), v.X, radius_m)
    return out


def solve_views(model: str, size: tuple[int, int], views: list[ViewData], target: Target,
           start: tuple[F64, F64, F64] | None = None, max_iter: int = 100, board_warp: bool = False,
           regularise: bool = False) -> tuple[BundleProblem, F64, F64, F64, int]:
    """Solve the bundle problem; ``board_warp`` (or a ``start`` whose vector carries the warp)
    also solves the target's two warp parameters (``kernels``), after the lens's; ``regularise``: with
    mrcal's regularisation (``build_problem``)."""
    nd = N_DIST[model]
    warp = board_warp or (start is not None and len(start[0]) > 4 + nd)
    p = build_problem(model, size, views, target if warp else None, regularise)
    raw_obs = p.obs.copy()
    n = 4 + nd + (2 if warp else 0)
    if start is None:
        c4, R, t = initial_estimate(views, size)
        c = np.concatenate([c4, np.zeros(n - 4)])
        free = np.zeros(n, dtype=bool)
        free[:5] = True                           # fx, fy, cx, cy and k1 / kappa
        c, R, t, it0 = levenberg_marquardt(p, c, R, t, free, max_iter=50)
    else:
        c, R, t = start
        it0 = 0
    free = np.ones(n, dtype=bool)
    c, R, t, it = levenberg_marquardt(p, c, R, t, free, max_iter=max_iter)
    it += it0
    if any(v.ellipse for v in views) and isinstance(target, CirclePlate):
        bias = np.zeros_like(raw_obs)
        for _ in range(5):
            new_bias = circle_bias(p, views, c, R, t, target.radius_m)
            change = float(np.nanmax(np.abs(new_bias - bias)))
            bias = new_bias
            p.obs = raw_obs - bias
            c, R, t, it1 = levenberg_marquardt(p, c, R, t, free, max_iter=max_iter)
            it += it1
            if change < 1e-4:
                break
    return p, c, R, t, it


CONSISTENT_FACTOR = 3.0
"""Outlier points are weighted out only where the residual scale is within this factor of the
points' stated precision (beyond it the residuals are mostly what the model does not fit)."""


def outlier_points(res_w: F64, kept: NDArray[np.bool_], views: list[ViewData]) -> tuple[NDArray[np.bool_], bool]:
    """The points (M,) whose weighted residual ``res_w`` (M, 2) exceeds ``POINT_OUTLIER_SIGMAS`` robust
    sigma of the ``kept`` points' ones, and whether they are detection failures to weight out: only
    where the detectors' stated precision explains the residual scale (within ``CONSISTENT_FACTOR`` of
    the median stated uncertainty; none stated: never). Otherwise they are what the model does not
    fit, to be flagged only (``reject_outlier_points``; the splined solver)."""
    comp = np.abs(res_w[kept].reshape(-1))
    comp = comp[np.isfinite(comp)]
    if comp.size == 0:
        return np.zeros(len(res_w), dtype=bool), False
    sigma_r = 1.4826 * float(np.median(comp))
    out = ~(np.linalg.norm(res_w, axis=1) <= POINT_OUTLIER_SIGMAS * max(sigma_r, 1e-9))
    stated = weighting_sigmas(views)
    return out, stated is not None and sigma_r <= CONSISTENT_FACTOR * float(np.median(stated))


def reject_outlier_points(views: list[ViewData], p: BundleProblem, c: F64, R: F64, t: F64) -> bool:
    """Weight out the points whose residual (weighted by their detection precision) exceeds
    ``POINT_OUTLIER_SIGMAS`` robust sigma of the kept points; True when the set changed.

    A few grossly wrong corners (a defocused, JPEG-compressed view's outer corners: 1 px off where
    the rest err by 0.04 px) otherwise pull the estimate (0.43 px projection error instead of
    ~0.05 on a rendered 640x480 set) and inflate the residual scale, and with it the reported
    uncertainty, for every point. Only where the detectors' stated precision explains the
    residuals (robust scale within ``CONSISTENT_FACTOR`` of the median stated uncertainty) is a
    5-sigma point a detection failure. Where a lens or board the model does not fit dominates
    (the real udacity sets: residuals 100x the stated precision) the largest residuals are that
    misfit at the image's edges: rejecting them cost cross-validation 8.0 -> 8.8 px (9x6) and,
    with neighbour-relative residuals and repeated rounds, 3.9 -> 508 px (GoPro). There the
    points are only flagged."""
    res = p.project(c, R, t) - p.obs
    kept = ~np.concatenate([np.zeros(len(v.X), dtype=bool) if v.rejected is None else v.rejected for v in views])
    out, detection_failures = outlier_points(res * base_weights(views)[:, None], kept, views)
    if not detection_failures or np.array_equal(out, ~kept):
        return False
    for k, v in enumerate(views):
        o = out[p.starts[k]:p.starts[k + 1]]
        if len(v.X) - int(o.sum()) < MIN_POINTS_PER_VIEW:
            o = np.zeros_like(o)        # too few left: the view outlier rule judges it instead
        v.rejected = o if o.any() else None
    return True


def base_weights(views: list[ViewData]) -> F64:
    """(M,) the points' detection weights, rejected points included."""
    return np.concatenate([np.ones(len(v.X)) if v.w is None else v.w for v in views])


def flag_outliers(p: BundleProblem, res: F64, base_w: F64 | None = None
                  ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Flag points (|e| > 5 robust sigma of the kept points, residuals weighted by the points'
    own precision ``base_w``, default the problem's weights) and views (RMS > 3x median view
    RMS). Points weighted out (weight 0 in the problem) are judged with their ``base_w``."""
    w = p.w if base_w is None else base_w
    res_w = res if w is None else res * w[:, None]
    kept = np.ones(len(res), dtype=bool) if p.w is None else p.w > 0
    comp = np.abs(res_w[kept].reshape(-1))
    comp = comp[np.isfinite(comp)]
    sigma_r = 1.4826 * float(np.median(comp)) if comp.size else 0.0
    pt = np.linalg.norm(res_w, axis=1) > POINT_OUTLIER_SIGMAS * max(sigma_r, 1e-9)
    mag = np.linalg.norm(res, axis=1)
    vr = np.array([np.sqrt(np.mean(mag[p.starts[k]:p.starts[k + 1]] ** 2)) for k in range(p.n_views)])
    med = float(np.median(vr))
    vw = vr > VIEW_OUTLIER_FACTOR * max(med, 1e-9)
    return pt, vw
