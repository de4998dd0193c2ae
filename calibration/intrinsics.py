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
   perspective bias of each mark (``calibration.conic.circle_centre_bias_px``) is recomputed from
   the current camera and poses and the solve repeated until the bias changes by < 1e-4 px
   (two or three rounds): the bias correction lives inside the estimation loop.
3. **Outliers** (rule): a point is an outlier when its residual length exceeds
   ``5 * sigma_r``, with ``sigma_r = 1.4826 * median(|residual component|)`` (a robust per-axis
   standard deviation); a view is an outlier when its RMS exceeds ``3 *`` the median view RMS.
   They are always flagged; with ``drop_outliers=True`` they are removed and the solve repeated once.
4. **Covariance**: ``sigma^2 (J^T J)^-1`` at the optimum with ``sigma^2 = sum(r^2) / (m - n)``;
   the intrinsics block is the inverse of the Schur complement, i.e. marginalised over the poses.
   That formula assumes independent pixel noise. Real detectors (and our rendered benchmark)
   make errors that are correlated within a view, which it cannot see; so a grouped view-level
   jackknife (up to 10 groups, each replicate warm-started) estimates the projection
   uncertainty empirically too, and when it is larger the analytic covariance is scaled up to
   match (``uncertainty.inflation``; both estimates are reported).
5. **Projection uncertainty** (mrcal's idea, shared/INTERFACES.md ``uncertainty.projection_rms_px``):
   rays through a grid of pixels are projected with perturbed intrinsics; a small rotation of the
   camera frame cannot be told from some intrinsics changes (principal point vs. pan/tilt), so the
   best rotation (fitted over the covered region) is compensated. The 2x2 covariance of each grid
   pixel's compensated projection follows linearly from the intrinsics covariance; its RMS over
   the covered grid cells is ``projection_rms_px``. Projection does not depend on the distance
   along a ray, so the working distance drops out (unlike mrcal, whose reference frame moves with
   the poses; marginalising over the poses and compensating the rotation plays that role here).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from calibration.camera_model import MODEL_NAMES, N_DIST, CameraModel, ModelName
from calibration.conic import circle_centre_bias_px
from calibration.geometry import make_transform
from calibration.observations import Detection
from calibration.targets import CirclePlate, Points3D, Target
from calibration.verdict import assess

F64 = NDArray[np.float64]

MIN_VIEWS: Final = 3
"""Fewer views cannot determine fx, fy, cx, cy from a planar target (Zhang)."""
MIN_POINTS_PER_VIEW: Final = 6
POINT_OUTLIER_SIGMAS: Final = 5.0
VIEW_OUTLIER_FACTOR: Final = 3.0
JACKKNIFE_GROUPS: Final = 10
JACKKNIFE_MIN_VIEWS: Final = 5


class CalibrationError(ValueError):
    """The data cannot produce a calibration (too few views or points, degenerate geometry)."""


# --------------------------------------------------------------------------------------------
# results


@dataclass
class ViewResult:
    """One image's part in the calibration."""

    image: str
    used: bool
    n_points: int = 0
    rms_px: float = float("nan")
    reason: str = ""
    outlier: bool = False
    n_outlier_points: int = 0
    T_cam_target: F64 | None = None
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"image": self.image, "rms_px": _fin(self.rms_px), "used": self.used,
                               "n_points": self.n_points}
        if self.reason:
            out["reason"] = self.reason
        if self.outlier:
            out["outlier"] = True
        if self.n_outlier_points:
            out["n_outlier_points"] = self.n_outlier_points
        if self.T_cam_target is not None:
            out["T_cam_target"] = self.T_cam_target.tolist()
        return out


@dataclass
class IntrinsicsResult:
    """A calibrated camera with its residuals, parameter covariance, uncertainty and verdict."""

    camera: CameraModel
    rms_px: float
    sigma_px: float
    views: list[ViewResult]
    param_names: list[str]
    covariance: F64
    """Intrinsics covariance (order of ``param_names``), marginalised over the view poses."""
    uncertainty: dict[str, Any]
    verdict: dict[str, Any]
    coverage: NDArray[np.int64]
    """(ny, nx) count of observed points per image cell (used views)."""
    uncertainty_map_px: F64
    """(ny, nx) 1-sigma projection uncertainty at each cell centre (rotation compensated)."""
    iterations: int = 0
    time_s: float = 0.0

    @property
    def param_sigmas(self) -> dict[str, float]:
        return {n: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, n in enumerate(self.param_names)}

    def to_json(self) -> dict[str, Any]:
        """The camera result file (shared/INTERFACES.md §4 ``cam.json``)."""
        out = self.camera.to_dict()
        out["rms_px"] = _fin(self.rms_px)
        out["views"] = [v.to_json() for v in self.views]
        out["uncertainty"] = self.uncertainty
        out["verdict"] = self.verdict
        out["parameters"] = {
            "names": self.param_names,
            "sigma": [self.param_sigmas[n] for n in self.param_names],
            "covariance": self.covariance.tolist(),
        }
        out["residual_sigma_px"] = _fin(self.sigma_px)
        out["n_views_used"] = sum(v.used for v in self.views)
        out["n_points_used"] = int(sum(v.n_points for v in self.views if v.used))
        out["solver"] = {"iterations": self.iterations, "time_s": round(self.time_s, 3)}
        return out


def _fin(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


# --------------------------------------------------------------------------------------------
# the vectorised model


def param_names(model: str) -> list[str]:
    names = {"opencv5": ["k1", "k2", "p1", "p2", "k3"],
             "opencv8": ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"],
             "division": ["kappa"]}[model]
    return ["fx", "fy", "cx", "cy", *names]


def intrinsics_vector(camera: CameraModel) -> F64:
    return np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.dist])


def camera_from_vector(model: str, size: tuple[int, int], c: ArrayLike) -> CameraModel:
    c = np.asarray(c, dtype=np.float64)
    K = np.array([[c[0], 0.0, c[2]], [0.0, c[1], c[3]], [0.0, 0.0, 1.0]])
    return CameraModel(cast(ModelName, model), size[0], size[1], K, c[4:].copy())


def rotations(rv: F64) -> F64:
    """(V, 3) rotation vectors to (V, 3, 3) matrices (Rodrigues, vectorised)."""
    rv = np.asarray(rv, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(rv, axis=1)
    small = th < 1e-12
    k = rv / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(rv), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3)[None] + s * Kx + (1 - c) * (Kx @ Kx)
    R[small] = np.eye(3)
    return R


def _project_normalized(model: str, c: F64, xy: F64) -> F64:
    from calibration.camera_model import distort_normalized

    d = distort_normalized(model, c[4:], xy)
    return np.column_stack([c[0] * d[:, 0] + c[2], c[1] * d[:, 1] + c[3]])


@dataclass
class _Problem:
    """Observations sorted by view: rows ``starts[v]:starts[v+1]`` belong to view ``v``."""

    model: str
    size: tuple[int, int]
    X: F64          # (M, 3) target points, metres
    obs: F64        # (M, 2) observed pixels (bias-corrected for circle marks)
    view: NDArray[np.int64]
    starts: NDArray[np.int64]

    @property
    def n_views(self) -> int:
        return len(self.starts) - 1

    def project(self, c: F64, R: F64, t: F64) -> F64:
        P = np.einsum("mij,mj->mi", R[self.view], self.X) + t[self.view]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / P[:, 2:3]
        xy[P[:, 2] <= 0] = np.nan
        return _project_normalized(self.model, c, xy)

    def residuals(self, c: F64, R: F64, t: F64) -> F64:
        return (self.project(c, R, t) - self.obs).reshape(-1)


def _intrinsic_steps(c: F64) -> F64:
    h = np.full(c.shape, 1e-7)
    h[:4] = 1e-5 * np.maximum(1.0, np.abs(c[:4]) * 1e-3)
    return h


def _jacobians(p: _Problem, c: F64, R: F64, t: F64, free: NDArray[np.bool_]) -> tuple[F64, F64]:
    """Central-difference Jacobians: (2M, n_free) for the intrinsics, (2M, 6) for each row's pose.

    The pose columns of all views are perturbed at once (a view's residuals depend only on its
    own pose), so the cost is 2 * (n_free + 6) residual evaluations whatever the view count.
    Rotations are perturbed on the left: ``R <- exp(w) R``.
    """
    hs = _intrinsic_steps(c)
    cols = []
    for i in np.nonzero(free)[0]:
        e = np.zeros_like(c)
        e[i] = hs[i]
        cols.append((p.residuals(c + e, R, t) - p.residuals(c - e, R, t)) / (2 * hs[i]))
    Jc = np.column_stack(cols) if cols else np.zeros((2 * len(p.X), 0))
    Jp = np.empty((2 * len(p.X), 6))
    hr, ht = 1e-7, 1e-7
    for k in range(3):
        w = np.zeros(3)
        w[k] = hr
        Rp = rotations(w[None])[0] @ R
        Rm = rotations(-w[None])[0] @ R
        Jp[:, k] = (p.residuals(c, Rp, t) - p.residuals(c, Rm, t)) / (2 * hr)
    for k in range(3):
        e3 = np.zeros(3)
        e3[k] = ht
        Jp[:, 3 + k] = (p.residuals(c, R, t + e3) - p.residuals(c, R, t - e3)) / (2 * ht)
    return Jc, Jp


@dataclass
class _Normal:
    A: F64
    B: F64   # (V, nc, 6)
    D: F64   # (V, 6, 6)
    gc: F64
    gv: F64  # (V, 6)


def _normal(p: _Problem, r: F64, Jc: F64, Jp: F64) -> _Normal:
    idx = 2 * p.starts[:-1]
    A = Jc.T @ Jc
    gc = Jc.T @ r
    D = np.add.reduceat(np.einsum("ri,rj->rij", Jp, Jp), idx, axis=0)
    B = np.add.reduceat(np.einsum("ri,rj->rij", Jc, Jp), idx, axis=0)
    gv = np.add.reduceat(Jp * r[:, None], idx, axis=0)
    return _Normal(A, B, D, gc, gv)


def _solve_damped(n: _Normal, lam: float) -> tuple[F64, F64]:
    A = n.A + lam * np.diag(np.diag(n.A))
    dD = np.einsum("vii->vi", n.D)
    D = n.D + lam * dD[:, :, None] * np.eye(6)[None]
    Dinv = np.linalg.inv(D)
    BDinv = n.B @ Dinv
    S = A - np.einsum("vij,vkj->ik", BDinv, n.B)
    rhs = -n.gc + np.einsum("vij,vj->i", BDinv, n.gv)
    if S.size:
        s = np.sqrt(np.maximum(np.diag(S), 1e-300))
        dc = np.linalg.lstsq(S / s[:, None] / s[None, :], rhs / s, rcond=1e-14)[0] / s
    else:
        dc = np.zeros(0)
    dv = np.einsum("vij,vj->vi", Dinv, -n.gv - np.einsum("vji,j->vi", n.B, dc))
    return dc, dv


def _cost(r: F64) -> float:
    return float(np.sum(r * r)) if np.all(np.isfinite(r)) else float("inf")


def _lm(p: _Problem, c: F64, R: F64, t: F64, free: NDArray[np.bool_], max_iter: int = 100
        ) -> tuple[F64, F64, F64, int]:
    """Levenberg-Marquardt (Marquardt's diagonal damping) with the Schur complement."""
    c, R, t = c.copy(), R.copy(), t.copy()
    r = p.residuals(c, R, t)
    cost = _cost(r)
    if not np.isfinite(cost):
        raise CalibrationError("the initial estimate puts target points behind the camera or outside "
                               "the lens model's range; check the target description")
    lam = 1e-3
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        Jc, Jp = _jacobians(p, c, R, t, free)
        n = _normal(p, r, Jc, Jp)
        improved = False
        while lam < 1e12:
            dc, dv = _solve_damped(n, lam)
            c_new = c.copy()
            c_new[free] += dc
            R_new = rotations(dv[:, :3]) @ R
            t_new = t + dv[:, 3:]
            r_new = p.residuals(c_new, R_new, t_new)
            cost_new = _cost(r_new)
            if cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                c, R, t, r, cost = c_new, R_new, t_new, r_new, cost_new
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved or rel < 1e-12:
            break
    return c, R, t, it


# --------------------------------------------------------------------------------------------
# set-up


@dataclass
class _ViewData:
    index: int
    image: str
    ids: NDArray[np.int64]
    X: F64
    uv: F64
    ellipse: bool


def _collect(detections: Sequence[Detection], target: Target,
             image_size: tuple[int, int] | None) -> tuple[list[_ViewData], list[ViewResult], tuple[int, int]]:
    if isinstance(target, Points3D):
        raise CalibrationError("calib intrinsics needs a planar target (chessboard, charuco, circle_plate, "
                               "circle_grid); for a 3D target use calib dlt")
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    sizes = [d.image_size for d in detections if d.found and d.image_size != (0, 0)]
    if image_size is None:
        if not sizes:
            raise CalibrationError("image size unknown: no detection carries it; pass image_size")
        # The most common size wins; views of another size are reported as not used.
        image_size = max(set(sizes), key=sizes.count)
    views: list[_ViewData] = []
    results: list[ViewResult] = []
    for k, d in enumerate(detections):
        vr = ViewResult(image=d.image, used=False)
        results.append(vr)
        if not d.found:
            vr.reason = d.reason or "target not found"
            continue
        if d.image_size not in ((0, 0), image_size):
            vr.reason = f"image size {d.image_size} differs from {image_size}"
            continue
        ids = np.asarray(d.ids, dtype=np.int64).reshape(-1)
        bad = [int(i) for i in ids if int(i) not in where]
        if bad:
            raise CalibrationError(f"{d.image}: point ids {bad[:5]} do not exist on the target "
                                   f"({target.describe()}); wrong target file?")
        use_ell = isinstance(target, CirclePlate) and d.uv_ellipse is not None
        uv = np.asarray(d.uv_ellipse if use_ell else d.uv, dtype=np.float64).reshape(-1, 2)
        ok = np.all(np.isfinite(uv), axis=1)
        if ok.sum() < MIN_POINTS_PER_VIEW:
            vr.reason = f"only {int(ok.sum())} points (need {MIN_POINTS_PER_VIEW})"
            continue
        X = tp.xyz_m[[where[int(i)] for i in ids[ok]]]
        views.append(_ViewData(k, d.image, ids[ok], X, uv[ok], use_ell))
        vr.n_points = int(ok.sum())
    return views, results, image_size


def _initial(views: list[_ViewData], size: tuple[int, int]) -> tuple[F64, F64, F64]:
    """Zhang's closed form for K (principal point at the centre), then IPPE poses."""
    obj = [v.X.astype(np.float32) for v in views]
    img = [v.uv.astype(np.float32) for v in views]
    try:
        K = cv2.initCameraMatrix2D(obj, img, size, 1.0)
    except cv2.error as exc:
        raise CalibrationError(f"closed-form initialisation failed ({exc.err}); are the views degenerate "
                               "(all parallel to each other)?") from exc
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError("closed-form initialisation failed: the views do not determine a focal "
                               "length (all views parallel? tilt the target between views)")
    # initCameraMatrix2D forces fx == fy from the mean; a wild value means degenerate views.
    R = np.empty((len(views), 3, 3))
    t = np.empty((len(views), 3))
    for k, v in enumerate(views):
        ok, rv, tv = cv2.solvePnP(v.X, v.uv, K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rv, tv = cv2.solvePnP(v.X, v.uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError(f"{v.image}: no initial pose (points degenerate?)")
        R[k] = cv2.Rodrigues(rv)[0]
        t[k] = tv.ravel()
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), R, t


def _build(model: str, size: tuple[int, int], views: list[_ViewData]) -> _Problem:
    counts = np.array([len(v.X) for v in views])
    return _Problem(model, size, np.vstack([v.X for v in views]), np.vstack([v.uv for v in views]),
                    np.repeat(np.arange(len(views)), counts).astype(np.int64),
                    np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))


def _bias(p: _Problem, views: list[_ViewData], c: F64, R: F64, t: F64, radius_m: float) -> F64:
    cam = camera_from_vector(p.model, p.size, c)
    out = np.zeros_like(p.obs)
    for k, v in enumerate(views):
        if v.ellipse:
            sl = slice(p.starts[k], p.starts[k + 1])
            out[sl] = circle_centre_bias_px(cam, make_transform(R[k], t[k]), v.X, radius_m)
    return out


def _solve(model: str, size: tuple[int, int], views: list[_ViewData], target: Target,
           start: tuple[F64, F64, F64] | None = None, max_iter: int = 100
           ) -> tuple[_Problem, F64, F64, F64, int]:
    p = _build(model, size, views)
    raw_obs = p.obs.copy()
    nd = N_DIST[model]
    if start is None:
        c4, R, t = _initial(views, size)
        c = np.concatenate([c4, np.zeros(nd)])
        free = np.zeros(4 + nd, dtype=bool)
        free[:5] = True                           # fx, fy, cx, cy and k1 / kappa
        c, R, t, it0 = _lm(p, c, R, t, free, max_iter=50)
    else:
        c, R, t = start
        it0 = 0
    free = np.ones(4 + nd, dtype=bool)
    c, R, t, it = _lm(p, c, R, t, free, max_iter=max_iter)
    it += it0
    if any(v.ellipse for v in views) and isinstance(target, CirclePlate):
        bias = np.zeros_like(raw_obs)
        for _ in range(5):
            new_bias = _bias(p, views, c, R, t, target.radius_m)
            change = float(np.nanmax(np.abs(new_bias - bias)))
            bias = new_bias
            p.obs = raw_obs - bias
            c, R, t, it1 = _lm(p, c, R, t, free, max_iter=max_iter)
            it += it1
            if change < 1e-4:
                break
    return p, c, R, t, it


# --------------------------------------------------------------------------------------------
# uncertainty


def _grid(size: tuple[int, int], nx: int = 16) -> tuple[F64, int, int]:
    w, h = size
    ny = max(4, int(round(nx * h / w)))
    us = (np.arange(nx) + 0.5) * w / nx - 0.5
    vs = (np.arange(ny) + 0.5) * h / ny - 0.5
    uu, vv = np.meshgrid(us, vs)
    return np.column_stack([uu.ravel(), vv.ravel()]), nx, ny


def coverage_counts(size: tuple[int, int], uv: F64, nx: int = 16) -> NDArray[np.int64]:
    """(ny, nx) number of observed points in each image cell."""
    w, h = size
    _, nx, ny = _grid(size, nx)
    cnt = np.zeros((ny, nx), dtype=np.int64)
    if len(uv):
        ix = np.clip((uv[:, 0] + 0.5) * nx / w, 0, nx - 1).astype(int)
        iy = np.clip((uv[:, 1] + 0.5) * ny / h, 0, ny - 1).astype(int)
        np.add.at(cnt, (iy, ix), 1)
    return cnt


def projection_jacobians(camera: CameraModel, pts_px: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """For the rays through ``pts_px``: (2N, n_intr) d(pixel)/d(intrinsics), (2N, 3)
    d(pixel)/d(camera rotation) and a validity mask (N,)."""
    rays = camera.unproject(pts_px)
    xy = rays[:, :2]
    c = intrinsics_vector(camera)
    valid = np.all(np.isfinite(xy), axis=1)
    xy = np.where(valid[:, None], xy, 0.0)
    hs = _intrinsic_steps(c)
    Jc = np.empty((2 * len(xy), len(c)))
    for i in range(len(c)):
        e = np.zeros_like(c)
        e[i] = hs[i]
        Jc[:, i] = ((_project_normalized(camera.model, c + e, xy)
                     - _project_normalized(camera.model, c - e, xy)) / (2 * hs[i])).reshape(-1)
    Jw = np.empty((2 * len(xy), 3))
    P = np.column_stack([xy, np.ones(len(xy))])
    h = 1e-7
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        Pp = P @ rotations(w[None])[0].T
        Pm = P @ rotations(-w[None])[0].T
        Jw[:, k] = ((_project_normalized(camera.model, c, Pp[:, :2] / Pp[:, 2:])
                     - _project_normalized(camera.model, c, Pm[:, :2] / Pm[:, 2:])) / (2 * h)).reshape(-1)
    bad = ~np.all(np.isfinite(Jc), axis=1) | ~np.all(np.isfinite(Jw), axis=1)
    valid &= ~bad.reshape(-1, 2).any(axis=1)
    return np.nan_to_num(Jc), np.nan_to_num(Jw), valid


def projection_uncertainty(camera: CameraModel, cov: F64, pts_px: F64, fit_mask: NDArray[np.bool_]
                           ) -> F64:
    """1-sigma projection uncertainty (px, RMS length of the 2D error) at each of ``pts_px``,
    after compensating the rotation that best explains the change over ``fit_mask`` points."""
    Jc, Jw, valid = projection_jacobians(camera, pts_px)
    m = np.repeat(fit_mask & valid, 2)
    A = Jw[m]
    if A.shape[0] >= 6:
        G = np.linalg.pinv(A) @ Jc[m]            # best rotation per unit intrinsics change
        M = Jc - Jw @ G
    else:
        M = Jc
    Mi = M.reshape(len(pts_px), 2, -1)
    var = np.einsum("nai,ij,naj->n", Mi, cov, Mi)
    out = np.sqrt(np.maximum(var, 0.0))
    out[~valid] = np.nan
    return out


def _named_points(size: tuple[int, int]) -> dict[str, tuple[float, float]]:
    w, h = size[0] - 1.0, size[1] - 1.0
    return {"centre": (w / 2, h / 2), "top_left": (0.0, 0.0), "top_right": (w, 0.0),
            "bottom_left": (0.0, h), "bottom_right": (w, h), "top": (w / 2, 0.0),
            "bottom": (w / 2, h), "left": (0.0, h / 2), "right": (w, h / 2)}


def uncertainty_summary(camera: CameraModel, cov: F64, coverage: NDArray[np.int64]
                        ) -> tuple[dict[str, Any], F64]:
    """The ``uncertainty`` block of ``cam.json`` and the per-cell map."""
    grid, nx, ny = _grid(camera.size, coverage.shape[1])
    covered = coverage.reshape(-1) > 0
    named = _named_points(camera.size)
    pts = np.vstack([grid, np.array(list(named.values()))])
    fit = np.concatenate([covered, np.zeros(len(named), dtype=bool)])
    s = projection_uncertainty(camera, cov, pts, fit)
    s_grid, s_named = s[: len(grid)], dict(zip(named, s[len(grid):], strict=True))
    s_whole = projection_uncertainty(camera, cov, grid, np.ones(len(grid), dtype=bool))

    def rms(a: F64) -> float:
        a = a[np.isfinite(a)]
        return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")

    summary = {
        "projection_rms_px": _fin(rms(s_grid[covered])),
        "projection_rms_whole_image_px": _fin(rms(s_whole)),
        "projection_max_px": _fin(float(np.nanmax(s_grid)) if np.any(np.isfinite(s_grid)) else float("nan")),
        "centre_px": _fin(float(s_named["centre"])),
        "corners_px": {k: _fin(float(s_named[k])) for k in ("top_left", "top_right", "bottom_left",
                                                             "bottom_right")},
        "edges_px": {k: _fin(float(s_named[k])) for k in ("top", "bottom", "left", "right")},
        "covered_fraction": float(covered.mean()),
        "method": "intrinsics covariance (marginalised over poses) propagated through projection of "
                  "rays through a pixel grid, best camera rotation compensated over the covered cells; "
                  "1-sigma RMS length of the pixel error",
    }
    return summary, s_grid.reshape(ny, nx)


# --------------------------------------------------------------------------------------------
# the public solver


def calibrate(detections: Sequence[Detection], target: Target, model: str = "opencv5", *,
              image_size: tuple[int, int] | None = None, drop_outliers: bool = False,
              jackknife: bool = True) -> IntrinsicsResult:
    """Calibrate one camera from detections of ``target`` (see the module docstring).

    ``jackknife``: also estimate the projection uncertainty by a grouped view-level jackknife and
    scale the analytic covariance up when the jackknife's value is larger.

    Raises CalibrationError with a message saying what to do when the data cannot determine
    the model (fewer than 3 usable views, too few points, all views parallel...).
    """
    t0 = time.perf_counter()
    if model not in MODEL_NAMES:
        raise CalibrationError(f"unknown model {model!r}; use one of {', '.join(MODEL_NAMES)}")
    views, results, size = _collect(detections, target, image_size)
    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"only {len(views)} usable view(s) of the target; a calibration needs "
                               f"at least {MIN_VIEWS} (10-20 recommended, tilted 20-45 deg about both axes)")
    n_par = 4 + N_DIST[model]
    n_obs = 2 * sum(len(v.X) for v in views)
    if n_obs <= n_par + 6 * len(views):
        raise CalibrationError(f"too few points ({n_obs // 2}) for {len(views)} views and the {model} model")
    p, c, R, t, iters = _solve(model, size, views, target)
    if drop_outliers:
        p0_res = (p.project(c, R, t) - p.obs)
        pt_out, view_out = _outliers(p, p0_res)
        if np.any(pt_out) or np.any(view_out):
            kept: list[_ViewData] = []
            keep_R, keep_t = [], []
            for k, v in enumerate(views):
                if view_out[k]:
                    results[v.index].reason = "outlier view (RMS > 3x median), dropped"
                    results[v.index].outlier = True
                    continue
                m = ~pt_out[p.starts[k]:p.starts[k + 1]]
                if m.sum() < MIN_POINTS_PER_VIEW:
                    results[v.index].reason = "too few points left after dropping outliers"
                    continue
                results[v.index].n_outlier_points = int((~m).sum())
                kept.append(_ViewData(v.index, v.image, v.ids[m], v.X[m], v.uv[m], v.ellipse))
                keep_R.append(R[k])
                keep_t.append(t[k])
            if len(kept) < MIN_VIEWS:
                raise CalibrationError(f"only {len(kept)} views left after dropping outliers; "
                                       f"need at least {MIN_VIEWS}")
            views = kept
            start = (c, np.array(keep_R), np.array(keep_t))
            p, c, R, t, it2 = _solve(model, size, views, target, start=start)
            iters += it2
    # final Jacobian, covariance
    free = np.ones(n_par, dtype=bool)
    r = p.residuals(c, R, t)
    Jc, Jp = _jacobians(p, c, R, t, free)
    nrm = _normal(p, r, Jc, Jp)
    dof = max(len(r) - n_par - 6 * p.n_views, 1)
    sigma2 = float(np.sum(r * r)) / dof
    S_inv, pose_cov = _marginals(nrm)
    cov = sigma2 * S_inv
    camera = camera_from_vector(model, size, c)
    res = (p.project(c, R, t) - p.obs)
    pt_out, view_out = _outliers(p, res)
    all_uv = []
    for k, v in enumerate(views):
        sl = slice(p.starts[k], p.starts[k + 1])
        vr = results[v.index]
        vr.used = True
        vr.n_points = len(v.X)
        e = res[sl]
        vr.rms_px = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        vr.T_cam_target = make_transform(R[k], t[k])
        vr.ids, vr.uv, vr.residuals_px = v.ids, v.uv, e
        vr.n_outlier_points = max(vr.n_outlier_points, int(pt_out[sl].sum()))
        if view_out[k]:
            vr.outlier = True
            vr.reason = "outlier view: RMS > 3x the median view RMS (drop_outliers removes it)"
        all_uv.append(v.uv)
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    coverage = coverage_counts(size, np.vstack(all_uv))
    unc, umap = uncertainty_summary(camera, cov, coverage)
    unc["projection_rms_analytic_px"] = unc["projection_rms_px"]
    unc["inflation"] = 1.0
    if jackknife and len(views) >= JACKKNIFE_MIN_VIEWS:
        grid, _, _ = _grid(size, coverage.shape[1])
        j = _jackknife_projection_rms(model, size, views, target, c, R, t, grid[coverage.reshape(-1) > 0])
        a = unc["projection_rms_px"]
        if a and np.isfinite(j) and j > a:
            # Detection errors correlated within a view make the analytic covariance optimistic;
            # the view-level jackknife sees them. Scale the analytic covariance up to match.
            cov = cov * (j / a) ** 2
            unc, umap = uncertainty_summary(camera, cov, coverage)
            unc["inflation"] = j / a
        unc["projection_rms_analytic_px"] = a
        unc["projection_rms_jackknife_px"] = _fin(j)
    names = param_names(model)
    sig = {n: float(np.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    normals = R[:, :, 2]
    verdict = assess(n_views=len(views), size=size, coverage=coverage, normals=normals, sigmas=sig,
                     values=dict(zip(names, c.tolist(), strict=True)), uncertainty=unc,
                     n_outlier_views=int(view_out.sum()))
    del pose_cov
    return IntrinsicsResult(camera=camera, rms_px=rms, sigma_px=float(np.sqrt(sigma2 / 2)), views=results,
                            param_names=names, covariance=cov, uncertainty=unc, verdict=verdict,
                            coverage=coverage, uncertainty_map_px=umap, iterations=iters,
                            time_s=time.perf_counter() - t0)


def _jackknife_projection_rms(model: str, size: tuple[int, int], views: list[_ViewData], target: Target,
                              c: F64, R: F64, t: F64, pts: F64) -> float:
    """Grouped delete-a-group jackknife over views (G = min(views, 10) groups, view k in group
    k mod G; replicates warm-started, at most 30 iterations): the RMS over ``pts`` of the
    jackknife standard deviation of each point's projection (best rotation compensated per
    replicate). Done in pixel space, not parameter space, because the rational model's
    coefficients wander along a flat valley that projection does not see."""
    G = min(len(views), JACKKNIFE_GROUPS)
    full = camera_from_vector(model, size, c)
    qs = []
    for g in range(G):
        keep = [k for k in range(len(views)) if k % G != g]
        _, cg, _, _, _ = _solve(model, size, [views[k] for k in keep], target, start=(c, R[keep], t[keep]),
                                max_iter=30)
        d = projection_difference(camera_from_vector(model, size, cg), full, pts)
        if len(d["diff_px"]) != len(pts):
            return float("nan")
        qs.append(d["diff_px"])
    Q = np.array(qs)                                   # (G, N, 2)
    dev = Q - Q.mean(axis=0)
    var = (G - 1) / G * np.sum(dev * dev, axis=(0, 2))
    return float(np.sqrt(np.mean(var)))


def _marginals(n: _Normal) -> tuple[F64, F64]:
    """Inverse of the Schur complement (intrinsics covariance / sigma^2) and the pose blocks."""
    Dinv = np.linalg.inv(n.D)
    BDinv = n.B @ Dinv
    S = n.A - np.einsum("vij,vkj->ik", BDinv, n.B)
    s = np.sqrt(np.maximum(np.diag(S), 1e-300))
    S_inv = np.linalg.pinv(S / s[:, None] / s[None, :], rcond=1e-15) / s[:, None] / s[None, :]
    pose = Dinv + np.einsum("vji,jk,vkl->vil", BDinv, S_inv, BDinv)
    return S_inv, pose


def _outliers(p: _Problem, res: F64) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Flag points (|e| > 5 robust sigma) and views (RMS > 3x median view RMS)."""
    comp = np.abs(res.reshape(-1))
    sigma_r = 1.4826 * float(np.median(comp)) if comp.size else 0.0
    mag = np.linalg.norm(res, axis=1)
    pt = mag > POINT_OUTLIER_SIGMAS * max(sigma_r, 1e-9)
    vr = np.array([np.sqrt(np.mean(mag[p.starts[k]:p.starts[k + 1]] ** 2)) for k in range(p.n_views)])
    med = float(np.median(vr))
    vw = vr > VIEW_OUTLIER_FACTOR * max(med, 1e-9)
    return pt, vw


# --------------------------------------------------------------------------------------------
# comparing cameras


def projection_difference(camera: CameraModel, reference: CameraModel, pts_px: ArrayLike | None = None,
                          fit_rotation: bool = True, nx: int = 32) -> dict[str, Any]:
    """How far ``camera`` projects the rays of ``reference``'s pixels from those pixels.

    For each pixel ``q`` (default: a grid over the whole image) the reference's ray is projected
    with ``camera`` after the rotation of the camera frame that minimises the total squared
    difference (``fit_rotation``). Returns RMS and max length (px), the rotation and the
    per-point differences.
    """
    if pts_px is None:
        pts, _, _ = _grid(reference.size, nx)
    else:
        pts = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    rays = reference.unproject(pts)
    ok = np.all(np.isfinite(rays), axis=1)
    rays, pts = rays[ok], pts[ok]
    c = intrinsics_vector(camera)

    def diff(w: F64) -> F64:
        P = rays @ rotations(w[None])[0].T
        q = _project_normalized(camera.model, c, P[:, :2] / P[:, 2:])
        d = q - pts
        return np.nan_to_num(d, nan=1e6).reshape(-1)

    w = np.zeros(3)
    if fit_rotation:
        w = least_squares(diff, w, method="lm", x_scale=1e-3).x
    d = diff(w).reshape(-1, 2)
    mag = np.linalg.norm(d, axis=1)
    return {"rms_px": float(np.sqrt(np.mean(mag**2))), "max_px": float(mag.max()),
            "rotation_deg": float(np.degrees(np.linalg.norm(w))), "diff_px": d, "points_px": pts}


def covered_points(result: IntrinsicsResult) -> F64:
    """Centres of the image cells the calibration data covered (for ``projection_difference``)."""
    grid, _, _ = _grid(result.camera.size, result.coverage.shape[1])
    return grid[result.coverage.reshape(-1) > 0]


def cross_validate(detections: Sequence[Detection], target: Target, model: str, k: int = 2, *,
                   image_size: tuple[int, int] | None = None, drop_outliers: bool = False) -> dict[str, Any]:
    """k-fold cross-validation (mrcal's idea): split the views into ``k`` disjoint folds
    (view ``i`` goes to fold ``i mod k``), calibrate each fold on its own, and report the
    projection difference between every pair of fold solutions over the image region the whole
    data set covered (best rotation compensated). Two solutions from independent data differ by
    about sqrt(2) times each one's projection uncertainty if the model fits the lens; a much
    larger difference means the model cannot describe the lens (or the data are inconsistent).
    """
    if k < 2:
        raise CalibrationError("cross-validation needs k >= 2 folds")
    found = [d for d in detections if d.found]
    if len(found) < MIN_VIEWS * k:
        raise CalibrationError(f"{len(found)} views with the target are too few for {k}-fold "
                               f"cross-validation (each fold needs {MIN_VIEWS}); use a smaller k")
    full = calibrate(found, target, model, image_size=image_size, drop_outliers=drop_outliers)
    pts = covered_points(full)
    fold_res = [calibrate(found[f::k], target, model, image_size=image_size, drop_outliers=drop_outliers)
                for f in range(k)]
    pairs = []
    for a in range(k):
        for b in range(a + 1, k):
            d = projection_difference(fold_res[a].camera, fold_res[b].camera, pts)
            pairs.append({"folds": [a, b], "rms_px": d["rms_px"], "max_px": d["max_px"]})
    rms = [pp["rms_px"] for pp in pairs]
    return {
        "k": k,
        "folds": [{"views": int(sum(v.used for v in r.views)), "rms_px": r.rms_px,
                   "projection_uncertainty_px": r.uncertainty["projection_rms_px"]} for r in fold_res],
        "pairs": pairs,
        "projection_difference_rms_px": float(np.mean(rms)),
        "projection_difference_max_px": float(np.max([pp["max_px"] for pp in pairs])),
        "expected_from_uncertainty_px": float(np.mean([
            np.hypot(fold_res[p["folds"][0]].uncertainty["projection_rms_px"] or 0.0,
                     fold_res[p["folds"][1]].uncertainty["projection_rms_px"] or 0.0) for p in pairs])),
    }


# --------------------------------------------------------------------------------------------
# synthetic data (tests, benchmarks, and a capture plan for operators)


def plan_views(camera: CameraModel, target: Target, n_views: int, rng: np.random.Generator,
               fill: float = 0.5, max_tilt_deg: float = 40.0, margin_px: float = 3.0) -> list[F64]:
    """``T_cam_target`` poses of a varied capture: the target tilted up to ``max_tilt_deg`` about
    both axes, placed so that it covers about ``fill`` of the image width, moved around so that
    the set covers the image corners. Every pose keeps all target points ``margin_px`` inside
    the image."""
    xyz = target.points().xyz_m
    x0, y0 = xyz[:, :2].min(axis=0)
    x1, y1 = xyz[:, :2].max(axis=0)
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]])
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    size_m = max(x1 - x0, y1 - y0)
    dist = camera.fx * size_m / (fill * camera.width)
    poses: list[F64] = []
    spots = [(0.0, 0.0), (-1, -1), (1, -1), (-1, 1), (1, 1), (0, -1), (0, 1), (-1, 0), (1, 0)]
    attempts = 0
    while len(poses) < n_views and attempts < 200 * n_views:
        attempts += 1
        k = len(poses)
        sx, sy = spots[k % len(spots)]
        tilt = np.radians(max_tilt_deg) * rng.uniform(-1, 1, 2)
        if k % 3 == 0:
            tilt[0] = np.radians(max_tilt_deg) * rng.choice([-1, 1]) * rng.uniform(0.5, 1)
        elif k % 3 == 1:
            tilt[1] = np.radians(max_tilt_deg) * rng.choice([-1, 1]) * rng.uniform(0.5, 1)
        spin = rng.uniform(-0.3, 0.3)
        Rm = rotations(np.array([[tilt[0], 0, 0]]))[0] @ rotations(np.array([[0, tilt[1], 0]]))[0] \
            @ rotations(np.array([[0, 0, spin]]))[0]
        d = dist * rng.uniform(0.85, 1.15)
        reach = 0.95
        for _ in range(15):
            q = np.array([[camera.cx + sx * reach * camera.width / 2,
                           camera.cy + sy * reach * camera.height / 2]])
            ray = camera.unproject(q)[0]
            t = ray / np.linalg.norm(ray) * d - Rm @ centre
            uv = camera.project(corners @ Rm.T + t)
            if np.all(np.isfinite(uv)) and np.all(uv >= margin_px) \
                    and np.all(uv[:, 0] <= camera.width - 1 - margin_px) \
                    and np.all(uv[:, 1] <= camera.height - 1 - margin_px):
                poses.append(make_transform(Rm, t))
                break
            reach *= 0.93
    if len(poses) < n_views:
        raise CalibrationError("could not plan the requested views: the target does not fit the image")
    return poses


def synthetic_detections(camera: CameraModel, target: Target, poses: Sequence[F64], noise_px: float,
                         rng: np.random.Generator) -> list[Detection]:
    """Project the target's points with ``camera`` and add Gaussian pixel noise (tests, benchmarks)."""
    tp = target.points()
    out = []
    for k, T in enumerate(poses):
        uv = camera.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, noise_px, (len(tp.ids), 2))
        out.append(Detection(image=f"view{k:02d}", found=True, ids=tp.ids.copy(), uv=uv,
                             image_size=camera.size))
    return out
