"""What bench/handeye.py and bench/handeye_robots.py share: the virtual camera and board, the peers
(OpenCV's seven methods and a plain joint reprojection refinement), and the Cramér-Rao bound.

The plain refinement is the bench's own reference, written here independently of cellctl's
solver: ``scipy.optimize.least_squares`` over X and Z only (rotation vector + translation each),
the recorded robot poses taken as exact, the pixel residuals of every target point minimised,
started from OpenCV's PARK solution. A real UR5e held-out set reached 1.15 px leave-one-out
with such a refinement, so cellctl's default must predict at least as well.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from calibration.camera_model import CameraModel
from calibration.geometry import invert, make_transform
from calibration.handeye import (
    OPENCV_METHODS,
    JointProblem,
    RobotNoise,
    Station,
    mean_pose,
    opencv_handeye,
    perturb,
    predict_cam_target,
    target_from_station,
)
from calibration.intrinsics.model import camera_from_vector, intrinsics_vector
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958.3], [0, 1900.0, 601.2], [0, 0, 1]]),
                  np.array([-0.12, 0.08, 0.0002, -0.0001, 0.0]))
BOARD = Chessboard(11, 8, 25.0)


def robot_world(setup: str, G: list[np.ndarray], C: list[np.ndarray], method: int) -> np.ndarray:
    """OpenCV's calibrateRobotWorldHandEye (solves the hand-eye transform and the target pose
    together, AX = ZB): base2gripper = inv(H_i), world = target; returns X = inv(gripper2cam)."""
    H = [g if setup == "eye-in-hand" else invert(g) for g in G]
    Hi = [invert(h) for h in H]
    _, _, R_g2c, t_g2c = cv2.calibrateRobotWorldHandEye([c[:3, :3] for c in C], [c[:3, 3] for c in C],
                                                        [h[:3, :3] for h in Hi], [h[:3, 3] for h in Hi],
                                                        method=method)
    return invert(make_transform(R_g2c, np.ravel(t_g2c)))


Peer = Callable[[str, list[np.ndarray], list[np.ndarray]], np.ndarray]


def _closed_form(method: str) -> Peer:
    return lambda setup, G, C: opencv_handeye(setup, G, C, method)


def _robot_world(method: int) -> Peer:
    return lambda setup, G, C: robot_world(setup, G, C, method)


PEERS: dict[str, Peer] = {m: _closed_form(m) for m in OPENCV_METHODS}
PEERS["RW_SHAH"] = _robot_world(cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
PEERS["RW_LI"] = _robot_world(cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI)


def plain_refinement(setup: str, stations: Sequence[Station], camera: CameraModel, intrinsics: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, CameraModel]:
    """X, Z (and, with ``intrinsics``, fx, fy, cx, cy and the distortion) by a plain joint
    reprojection refinement (module docstring), from OpenCV's PARK; returns (X, Z, camera)."""
    G = [s.G for s in stations]
    C = [s.C for s in stations]
    X0 = opencv_handeye(setup, G, C, "PARK")
    Z0 = mean_pose([target_from_station(setup, X0, g, c) for g, c in zip(G, C, strict=True)])
    c0 = intrinsics_vector(camera)
    n_c = len(c0) if intrinsics else 0

    def cam_at(p: np.ndarray) -> CameraModel:
        return camera_from_vector(camera.model, camera.size, c0 + p[12:]) if n_c else camera

    def res(p: np.ndarray) -> np.ndarray:
        X, Z, cam = perturb(X0, p[:6]), perturb(Z0, p[6:12]), cam_at(p)
        out = []
        for s in stations:
            Cp = predict_cam_target(setup, X, Z, s.G)
            out.append((cam.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv).ravel())
        return np.concatenate(out)

    scale = np.r_[np.full(12, 1e-3), np.maximum(np.abs(c0), 1e-3) * 1e-3][: 12 + n_c]
    sol = least_squares(res, np.zeros(12 + n_c), method="lm", x_scale=scale)
    return perturb(X0, sol.x[:6]), perturb(Z0, sol.x[6:12]), cam_at(sol.x)


def loo_px(setup: str, stations: Sequence[Station], camera: CameraModel,
           fit: Callable[[Sequence[Station]], tuple[Any, ...]]) -> dict[str, float]:
    """Leave-one-out prediction of ``fit`` (stations -> X, Z or X, Z, camera): pixel RMS over every
    held-out point, and the RMS target-position miss (mm)."""
    e_px, e_mm = [], []
    for i, s in enumerate(stations):
        rest = [t for k, t in enumerate(stations) if k != i]
        try:
            out = fit(rest)
        except cv2.error:
            e_px.append(np.full((len(s.obj), 2), np.nan))
            e_mm.append(np.nan)
            continue
        X, Z = out[0], out[1]
        cam = out[2] if len(out) > 2 else camera
        Cp = predict_cam_target(setup, X, Z, s.G)
        e_px.append(cam.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv)
        e_mm.append(1e3 * float(np.linalg.norm(Cp[:3, 3] - s.C[:3, 3])))
    E = np.vstack(e_px)
    return {"px": float(np.sqrt(np.nanmean(np.sum(E**2, axis=1)))), "mm": float(np.sqrt(np.nanmean(np.square(e_mm))))}


def peer_fit(setup: str, m: str) -> Callable[[Sequence[Station]], tuple[np.ndarray, np.ndarray]]:
    """Stations -> (X, Z) with OpenCV method ``m`` (Z the mean of the per-station target poses)."""
    def fit(st: Sequence[Station]) -> tuple[np.ndarray, np.ndarray]:
        X = PEERS[m](setup, [s.G for s in st], [s.C for s in st])
        return X, mean_pose([target_from_station(setup, X, s.G, s.C) for s in st])
    return fit


def cramer_rao(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float, noise: RobotNoise,
               X_true: np.ndarray, Z_true: np.ndarray) -> tuple[float, float]:
    """RMS rotation (deg) and translation (mm) error of X that an unbiased estimator cannot beat on
    data generated by the stated model (pixel σ, robot noise): sqrt(trace) of the inverse Fisher
    information, the whitened Jacobian of the model at the truth."""
    job = JointProblem(setup, stations, camera, sigma_px, noise, X_true, Z_true)
    x = np.zeros(job.n_params)
    J = job.jacobian(x, job.residuals(x))
    cov = np.linalg.inv(np.einsum("ij,ik->jk", J, J))
    return float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))), float(1e3 * np.sqrt(np.trace(cov[3:6, 3:6])))


def fmt_noise(n: RobotNoise) -> str:
    return f"{n.sigma_mm:g} mm / {n.sigma_deg:g}°"


def median_method(s: dict[str, Any], kind: str) -> float:
    """The median over OpenCV's seven methods of their median error (``kind``: rot or trans)."""
    return float(np.median([s[m + "_" + kind] for m in PEERS]))
