"""Target pose from one view with a known camera: ``T_cam_target``, its RMS and covariance.

OpenCV's non-iterative solvers do the search: the observed pixels are undistorted to ideal
normalized coordinates (our models, including the division model, which OpenCV cannot undistort),
then ``cv2.solvePnPGeneric`` with SQPnP and, for coplanar points, IPPE (which returns both
planar solutions). The candidate with the smallest reprojection residual through the full lens
model wins and is refined by Levenberg-Marquardt (``scipy.optimize.least_squares``) on pixel
residuals. The 6x6 covariance is ``sigma^2 (J^T J)^-1`` in the order ``[wx, wy, wz, tx, ty, tz]``:
a small rotation vector applied on the left of the rotation (radians) and the translation (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from calibration import CalibrationError
from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3, make_transform

F64 = NDArray[np.float64]


class PoseEstimationError(CalibrationError):
    """Too few or degenerate points for a pose."""


@dataclass
class PoseResult:
    T_cam_target: F64
    rms_px: float
    covariance: F64
    residuals_px: F64
    method: str

    @property
    def sigma_rot_deg(self) -> float:
        return float(np.degrees(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0))))

    @property
    def sigma_trans_mm(self) -> float:
        return float(1e3 * np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))

    def to_json(self) -> dict[str, Any]:
        return {"T_cam_target": self.T_cam_target.tolist(), "rms_px": self.rms_px,
                "n_points": len(self.residuals_px), "method": self.method,
                "covariance": self.covariance.tolist(),
                "covariance_order": ["wx_rad", "wy_rad", "wz_rad", "tx_m", "ty_m", "tz_m"],
                "uncertainty": {"rot_deg": self.sigma_rot_deg, "trans_mm": self.sigma_trans_mm}}


def _rot(w: F64) -> F64:
    return exp_so3(np.asarray(w, dtype=np.float64).reshape(3))


def _residuals(camera: CameraModel, X: F64, uv: F64, R0: F64, x: F64, w: F64 | None = None) -> F64:
    R = _rot(x[:3]) @ R0
    P = X @ R.T + x[3:]
    r = camera.project(P) - uv
    return np.nan_to_num((r if w is None else r * w[:, None]).reshape(-1), nan=1e6)


def estimate_pose(camera: CameraModel, points_m: ArrayLike, uv_px: ArrayLike,
                  weights: ArrayLike | None = None) -> PoseResult:
    """Pose of a target whose points ``points_m`` (N, 3, target frame) are seen at ``uv_px``.

    ``weights``: (N,) relative weights of the points' pixel residuals (``1 / sigma``, e.g. from
    ``calibration.observations.point_weights``); the refinement and the covariance use them,
    ``rms_px`` and ``residuals_px`` stay unweighted pixels."""
    X = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    w = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w is not None and (len(w) != len(uv) or not np.all(np.isfinite(w) & (w > 0))):
        raise PoseEstimationError(f"weights must be {len(uv)} positive finite numbers, one per point")
    if len(X) != len(uv):
        raise PoseEstimationError(f"{len(X)} target points but {len(uv)} image points")
    if len(X) < 4:
        raise PoseEstimationError(f"a pose needs at least 4 points, got {len(X)}")
    xy = camera.undistort_normalized(camera.pixels_to_normalized(uv))
    if not np.all(np.isfinite(xy)):
        raise PoseEstimationError("some image points lie outside the lens model's valid range")
    centred = X - X.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-12):
        raise PoseEstimationError("the target points are collinear; a pose needs points spanning a plane")
    planar = sv[2] < 1e-6 * sv[0]
    eye = np.eye(3)
    cands: list[tuple[str, F64, F64]] = []
    methods = [("sqpnp", cv2.SOLVEPNP_SQPNP)]
    if planar:
        methods.append(("ippe", cv2.SOLVEPNP_IPPE))
    for name, flag in methods:
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, xy, eye, None, flags=flag)
        except cv2.error:
            continue
        for k in range(n):
            cands.append((name, np.asarray(rvecs[k], dtype=np.float64).ravel(),
                          np.asarray(tvecs[k], dtype=np.float64).ravel()))
    if not cands:
        raise PoseEstimationError("no pose found (degenerate point configuration?)")
    best = None
    for name, rv, tv in cands:
        R = _rot(rv)
        r = _residuals(camera, X, uv, R, np.concatenate([np.zeros(3), tv]))
        cost = float(np.sum(r * r))
        if best is None or cost < best[0]:
            best = (cost, name, R, tv)
    if best is None:  # cands is not empty, so only a bug gets here
        raise PoseEstimationError("internal error: no candidate pose was scored")
    _, name, R0, t0 = best
    sol = least_squares(lambda x: _residuals(camera, X, uv, R0, x, w), np.concatenate([np.zeros(3), t0]),
                        method="lm", x_scale=np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3]))
    x = sol.x
    R = _rot(x[:3]) @ R0
    r = sol.fun
    # Jacobian at the optimum with respect to a fresh left perturbation about the solution.
    J = np.empty((len(r), 6))
    h = 1e-7
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        base = np.concatenate([np.zeros(3), x[3:]])
        J[:, k] = (_residuals(camera, X, uv, R, base + e, w) - _residuals(camera, X, uv, R, base - e, w)) / (2 * h)
    dof = max(len(r) - 6, 1)
    sigma2 = float(np.sum(r * r)) / dof
    cov = np.asarray(sigma2 * np.linalg.pinv(J.T @ J), dtype=np.float64)
    res = r.reshape(-1, 2) if w is None else r.reshape(-1, 2) / w[:, None]
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    return PoseResult(make_transform(R, x[3:]), rms, cov, res, name)
