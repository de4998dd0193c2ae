"""Target pose ``T_cam_target`` by a named solver: ``rpnp`` (ours, :mod:`calibration.pose.rpnp`),
``sqpnp``, ``ippe`` (coplanar points only) or ``epnp`` (OpenCV's), or ``auto``
(:func:`calibration.pose.pnp.estimate_pose`: SQPnP, plus IPPE on coplanar points).

Every solver works on ideal normalized coordinates (our lens models undistort the pixels, the
division model included); its candidates are each refined by Levenberg-Marquardt on pixel
residuals through the full camera model (:func:`refine_pose`, the same cost and covariance as
``calibration.pose.pnp``), and the refined candidate with the smallest residual wins. ``raw=True``
skips the refinement (the bench compares the solvers themselves).
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform
from calibration.pose.pnp import PoseEstimationError, PoseResult, estimate_pose
from calibration.pose.rpnp import RPnPError, rpnp

F64 = NDArray[np.float64]

METHODS: Final[tuple[str, ...]] = ("auto", "rpnp", "sqpnp", "ippe", "epnp")
_OPENCV_FLAGS: Final[dict[str, int]] = {"sqpnp": cv2.SOLVEPNP_SQPNP, "ippe": cv2.SOLVEPNP_IPPE,
                                         "epnp": cv2.SOLVEPNP_EPNP}
_MAX_REFINED: Final = 3
_CANDIDATE_COST_RATIO: Final = 10.0


def _rot(w: F64) -> F64:
    R, _ = cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)


def _residuals(camera: CameraModel, X: F64, uv: F64, R0: F64, x: F64) -> F64:
    P = X @ (_rot(x[:3]) @ R0).T + x[3:]
    return np.nan_to_num((camera.project(P) - uv).reshape(-1), nan=1e6)


def refine_pose(camera: CameraModel, X: F64, uv: F64, R0: F64, t0: F64, method: str) -> PoseResult:
    """Levenberg-Marquardt on pixels from ``(R0, t0)``; covariance ``σ² (JᵀJ)⁻¹`` in the order
    ``[wx, wy, wz, tx, ty, tz]`` (left rotation perturbation in radians, translation in metres)."""
    sol = least_squares(lambda x: _residuals(camera, X, uv, R0, x), np.concatenate([np.zeros(3), t0]),
                        method="lm", x_scale=np.full(6, 1e-3))
    R = _rot(sol.x[:3]) @ R0
    t = np.asarray(sol.x[3:], dtype=np.float64)
    return _result(camera, X, uv, R, t, method)


def _result(camera: CameraModel, X: F64, uv: F64, R: F64, t: F64, method: str) -> PoseResult:
    base = np.concatenate([np.zeros(3), t])
    r = _residuals(camera, X, uv, R, base)
    J = np.empty((len(r), 6))
    h = 1e-7
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        J[:, k] = (_residuals(camera, X, uv, R, base + e) - _residuals(camera, X, uv, R, base - e)) / (2 * h)
    sigma2 = float(r @ r) / max(len(r) - 6, 1)
    cov = np.asarray(sigma2 * np.linalg.pinv(J.T @ J), dtype=np.float64)
    res = r.reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    return PoseResult(make_transform(R, t), rms, cov, res, method)


def _prepare(camera: CameraModel, points_m: ArrayLike, uv_px: ArrayLike) -> tuple[F64, F64, F64, bool]:
    X = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    if len(X) != len(uv):
        raise PoseEstimationError(f"{len(X)} target points but {len(uv)} image points")
    if len(X) < 4:
        raise PoseEstimationError(f"a pose needs at least 4 points, got {len(X)} (3 points give up to four "
                                  "poses that cannot be told apart)")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv))):
        raise PoseEstimationError("the points contain NaN or infinity")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-12):
        raise PoseEstimationError("the target points are collinear; a pose needs points spanning a plane")
    xy = camera.undistort_normalized(camera.pixels_to_normalized(uv))
    if not np.all(np.isfinite(xy)):
        raise PoseEstimationError("some image points lie outside the lens model's valid range")
    return X, uv, xy, bool(sv[2] < 1e-6 * sv[0])


def _plane_mirror(X: F64, R: F64, t: F64) -> tuple[F64, F64]:
    """The other pose a plane can take for nearly the same image: tilted the other way about the
    line of sight through its centroid (the two-fold ambiguity IPPE returns as its second
    solution). Half-turn about the plane's normal, then about the line of sight; exact for a
    frontal plane (the two half-turns cancel), a start for the refinement otherwise."""
    centre = X.mean(axis=0)
    n_obj = np.linalg.svd(X - centre)[2][2]
    c_cam = R @ centre + t
    v = c_cam / np.linalg.norm(c_cam)
    Rm = _rot(np.pi * v) @ R @ _rot(np.pi * n_obj)
    return Rm, c_cam - Rm @ centre


def candidates(method: str, X: F64, xy: F64, planar: bool) -> list[tuple[F64, F64]]:
    """Initial poses ``(R, t)`` of one solver on ideal normalized coordinates."""
    if method == "rpnp":
        try:
            found = [(R, t) for R, t, _ in rpnp(X, xy)]
        except RPnPError as exc:
            raise PoseEstimationError(str(exc)) from exc
        return found + [_plane_mirror(X, R, t) for R, t in found] if planar else found
    if method not in _OPENCV_FLAGS:
        raise PoseEstimationError(f"unknown pose method {method!r}; use one of {', '.join(METHODS)}")
    if method == "ippe" and not planar:
        raise PoseEstimationError("ippe needs coplanar target points; use rpnp, sqpnp or epnp for a 3D target")
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, xy, np.eye(3), None, flags=_OPENCV_FLAGS[method])
    except cv2.error as exc:
        raise PoseEstimationError(f"{method} failed on these points ({exc.err})") from exc
    return [(_rot(np.asarray(rvecs[k]).ravel()), np.asarray(tvecs[k], dtype=np.float64).ravel()) for k in range(n)]


def estimate_pose_by(camera: CameraModel, points_m: ArrayLike, uv_px: ArrayLike, method: str = "auto",
                     raw: bool = False) -> PoseResult:
    """``T_cam_target`` of target points ``points_m`` (N, 3, target frame) seen at ``uv_px`` by ``method``.

    Raises PoseEstimationError (a ValueError) naming what is wrong: unknown method, fewer than 4
    points, collinear points, IPPE on a 3D target, no solution.
    """
    if method not in METHODS:
        raise PoseEstimationError(f"unknown pose method {method!r}; use one of {', '.join(METHODS)}")
    X, uv, xy, planar = _prepare(camera, points_m, uv_px)
    if method == "auto":
        return estimate_pose(camera, X, uv)  # its own refinement; raw does not apply
    cands = candidates(method, X, xy, planar)
    if not cands:
        raise PoseEstimationError(f"{method} found no pose (degenerate point configuration?)")
    scored = sorted(((float(np.sum(_residuals(camera, X, uv, R, np.concatenate([np.zeros(3), t])) ** 2)), R, t)
                     for R, t in cands), key=lambda c: c[0])
    if raw:
        return _result(camera, X, uv, scored[0][1], scored[0][2], method)
    best: PoseResult | None = None
    for cost, R, t in scored[:_MAX_REFINED]:
        if best is not None and cost > _CANDIDATE_COST_RATIO * scored[0][0] + 1e-12:
            break
        res = refine_pose(camera, X, uv, R, t, method)
        if best is None or res.rms_px < best.rms_px:
            best = res
    if best is None:  # pragma: no cover - scored is never empty here
        raise PoseEstimationError(f"{method} found no pose")
    return best
