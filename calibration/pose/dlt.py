"""Camera from one view of a non-coplanar 3D target: DLT, then a nonlinear refinement.

1. The 3x4 projection matrix by the normalized DLT (Hartley: points centred and scaled, then the
   SVD null vector), decomposed into ``K [R | t]`` by ``cv2.decomposeProjectionMatrix``.
2. A Levenberg-Marquardt refinement (``scipy.optimize.least_squares``) of fx, fy, cx, cy, the pose
   and, when enough points exist, distortion: radial ``k1`` (opencv5) or ``kappa`` (division) from
   ``MIN_POINTS_K1`` points, ``k1, k2`` from ``MIN_POINTS_K2``. Skew is fixed at 0.
3. Covariance ``sigma^2 (J^T J)^-1`` (intrinsics block marginalised over the pose) and the
   projection uncertainty as in ``calibration.intrinsics``.

Coplanar points cannot determine a camera from one view (the DLT's null space is 4-dimensional):
they are refused with a message pointing to ``calib intrinsics``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from calibration import CalibrationError
from calibration.camera_model import N_DIST, CameraModel
from calibration.geometry import make_transform
from calibration.intrinsics import (
    camera_from_vector,
    coverage_counts,
    param_names,
    rotations,
    uncertainty_summary,
)

F64 = NDArray[np.float64]

MIN_POINTS: Final = 6
MIN_POINTS_K1: Final = 12
MIN_POINTS_K2: Final = 20
COPLANAR_RATIO: Final = 1e-3
"""Points are coplanar when the smallest spread (singular value) is below this fraction of the largest."""


class DLTError(CalibrationError):
    """The points cannot determine a camera (too few, coplanar, inconsistent)."""


@dataclass
class DLTResult:
    camera: CameraModel
    T_cam_target: F64
    rms_px: float
    residuals_px: F64
    free_params: list[str]
    covariance: F64
    uncertainty: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        out = self.camera.to_dict()
        out.update({
            "rms_px": self.rms_px,
            "views": [{"image": "dlt", "rms_px": self.rms_px, "used": True,
                       "n_points": len(self.residuals_px), "T_cam_target": self.T_cam_target.tolist()}],
            "T_cam_target": self.T_cam_target.tolist(),
            "uncertainty": self.uncertainty,
            "parameters": {"names": self.free_params,
                           "sigma": np.sqrt(np.maximum(np.diag(self.covariance), 0.0)).tolist(),
                           "covariance": self.covariance.tolist()},
            "method": "dlt",
        })
        return out


def _normalizer(P: F64) -> F64:
    d = P.shape[1]
    c = P.mean(axis=0)
    s = np.sqrt(d) / max(float(np.mean(np.linalg.norm(P - c, axis=1))), 1e-12)
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def dlt_matrix(points_m: F64, uv_px: F64) -> F64:
    """The 3x4 projection matrix (ideal pinhole) by the normalized DLT."""
    T3 = _normalizer(points_m)
    T2 = _normalizer(uv_px)
    X = (T3 @ np.column_stack([points_m, np.ones(len(points_m))]).T).T
    x = (T2 @ np.column_stack([uv_px, np.ones(len(uv_px))]).T).T
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = X
    A[0::2, 8:12] = -x[:, 0:1] * X
    A[1::2, 4:8] = X
    A[1::2, 8:12] = -x[:, 1:2] * X
    _, _, Vt = np.linalg.svd(A)
    Pn = Vt[-1].reshape(3, 4)
    P = np.linalg.inv(T2) @ Pn @ T3
    return np.asarray(P / np.linalg.norm(P[2, :3]), dtype=np.float64)


def calibrate_dlt(points_m: ArrayLike, uv_px: ArrayLike, image_size: tuple[int, int] | None = None,
                  model: str = "opencv5", distortion: bool = True) -> DLTResult:
    """Camera (``model`` opencv5 or division) and ``T_cam_target`` from one view of a 3D target."""
    X = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    if model not in ("opencv5", "division"):
        raise DLTError(f"DLT supports the opencv5 and division models, not {model!r}")
    if len(X) != len(uv):
        raise DLTError(f"{len(X)} target points but {len(uv)} image points")
    if len(X) < MIN_POINTS:
        raise DLTError(f"DLT needs at least {MIN_POINTS} points, got {len(X)}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv))):
        raise DLTError("points contain NaN or infinity")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[2] < COPLANAR_RATIO * sv[0]:
        raise DLTError(f"the target points are coplanar (out-of-plane spread {sv[2] / sv[0]:.1e} of the "
                       "in-plane spread): one view of a plane cannot determine a camera; use a 3D target "
                       "or calib intrinsics with several tilted views of the plane")
    P = dlt_matrix(X, uv)
    # Points must lie in front of the camera.
    depth = (P @ np.column_stack([X, np.ones(len(X))]).T)[2]
    if np.median(depth) < 0:
        P = -P
    K, R, C, *_ = cv2.decomposeProjectionMatrix(P)
    K = K / K[2, 2]
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R
    if np.linalg.det(R) < 0:
        raise DLTError("the DLT solution is not a proper camera (mirror); check point ids and coordinates")
    Cc = (C[:3] / C[3]).ravel()
    t = -R @ Cc
    if image_size is None:
        image_size = (max(1, int(round(2 * K[0, 2] + 1))), max(1, int(round(2 * K[1, 2] + 1))))
    n = len(X)
    n_dist = N_DIST[model]
    free_dist = 0 if not distortion else (2 if n >= MIN_POINTS_K2 and model == "opencv5" else
                                          1 if n >= MIN_POINTS_K1 else 0)
    c0 = np.concatenate([[abs(K[0, 0]), abs(K[1, 1]), K[0, 2], K[1, 2]], np.zeros(n_dist)])

    def unpack(x: F64) -> tuple[F64, F64, F64]:
        c = c0.copy()
        c[:4] = x[:4]
        c[4:4 + free_dist] = x[4:4 + free_dist]
        Rm = rotations(x[-6:-3][None])[0] @ R
        return c, Rm, x[-3:]

    def resid(x: F64) -> F64:
        c, Rm, tv = unpack(x)
        cam = camera_from_vector(model, image_size, c)
        return np.nan_to_num((cam.project(X @ Rm.T + tv) - uv).reshape(-1), nan=1e6)

    x0 = np.concatenate([c0[:4], np.zeros(free_dist), np.zeros(3), t])
    if 2 * n <= len(x0):
        raise DLTError(f"{n} points are too few for {len(x0)} parameters")
    scale = np.concatenate([np.full(4, 1.0), np.full(free_dist, 1e-3), np.full(6, 1e-3)])
    sol = least_squares(resid, x0, method="lm", x_scale=scale)
    c, Rm, tv = unpack(sol.x)
    camera = camera_from_vector(model, image_size, c)
    r = sol.fun
    J = np.asarray(sol.jac, dtype=np.float64)
    dof = max(len(r) - len(x0), 1)
    sigma2 = float(np.sum(r * r)) / dof
    cov_full = sigma2 * np.linalg.pinv(J.T @ J)
    names_all = param_names(model)
    free_names = names_all[: 4 + free_dist]
    cov_free = cov_full[: 4 + free_dist, : 4 + free_dist]
    cov_intr = np.zeros((len(names_all), len(names_all)))
    cov_intr[: 4 + free_dist, : 4 + free_dist] = cov_free
    unc, _ = uncertainty_summary(camera, cov_intr, coverage_counts(image_size, uv))
    res = r.reshape(-1, 2)
    return DLTResult(camera=camera, T_cam_target=make_transform(Rm, tv),
                     rms_px=float(np.sqrt(np.mean(np.sum(res * res, axis=1)))), residuals_px=res,
                     free_params=free_names, covariance=np.asarray(cov_free, dtype=np.float64),
                     uncertainty=unc)
