"""Virtual-cell hand-eye data with truth (tests and bench/handeye.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera_model import CameraModel
from calibration.geometry import (
    exp_so3,
    invert,
    make_transform,
)
from calibration.handeye import Mat4, RobotNoise, perturb
from calibration.observations import Detection
from calibration.targets import Target


# --------------------------------------------------------------------------------------------
# virtual-cell data (tests and bench/handeye.py)
# --------------------------------------------------------------------------------------------
@dataclass
class SimulatedHandEye:
    """Generated hand-eye data with its truth."""

    setup: str
    camera: CameraModel
    target: Target
    X_true: Mat4
    Z_true: Mat4
    G_true: list[Mat4]
    G_recorded: list[Mat4]
    C_true: list[Mat4]
    detections: list[Detection]


def simulate_handeye(setup: str, n_poses: int, rng: np.random.Generator, *, camera: CameraModel,
                     target: Target, robot_noise: RobotNoise | None = None, pixel_sigma_px: float = 0.05,
                     distance_m: tuple[float, float] = (0.38, 0.52), max_tilt_deg: float = 35.0,
                     max_roll_deg: float = 60.0, X_true: Mat4 | None = None, Z_true: Mat4 | None = None
                     ) -> SimulatedHandEye:
    """Virtual-cell stations: target poses in the camera spread over distance, tilt (about a
    random in-plane axis) and roll, robot poses from the truth through the model of this module,
    then the recorded robot poses perturbed by ``robot_noise`` (the module's noise model) and the
    projected points by Gaussian pixel noise. Every station sees the whole target."""
    tp = target.points()
    centre = tp.xyz_m.mean(axis=0)
    if X_true is None:
        X_true = (make_transform(exp_so3([0.05, -0.08, 1.6]), [0.032, -0.051, 0.085]) if setup == "eye-in-hand"
                  else make_transform(exp_so3([2.9, 0.35, -0.2]), [0.45, -0.12, 0.95]))
    if Z_true is None:
        Z_true = (make_transform(exp_so3([0.02, -0.03, 0.7]), [0.55, 0.05, 0.02]) if setup == "eye-in-hand"
                  else make_transform(exp_so3([0.1, 3.0, 0.05]), [0.01, 0.02, 0.12]))
    Cs: list[Mat4] = []
    while len(Cs) < n_poses:
        z = rng.uniform(*distance_m)
        p = np.array([rng.uniform(-0.12, 0.12) * z, rng.uniform(-0.08, 0.08) * z, z])
        ang = np.radians(rng.uniform(0.3, 1.0) * max_tilt_deg)
        phi = rng.uniform(0, 2 * np.pi)
        roll = np.radians(rng.uniform(-max_roll_deg, max_roll_deg))
        R = exp_so3(ang * np.array([np.cos(phi), np.sin(phi), 0.0])) @ exp_so3([0.0, 0.0, roll])
        Cm = make_transform(R, p - R @ centre)
        uv = camera.project(tp.xyz_m @ R.T + Cm[:3, 3])
        if np.all(np.isfinite(uv)) and np.all((uv > 20) & (uv < np.array(camera.size) - 21)):
            Cs.append(Cm)
    noise = robot_noise or RobotNoise()
    G_true, G_rec, dets = [], [], []
    for k, Cm in enumerate(Cs):
        G = Z_true @ invert(Cm) @ invert(X_true) if setup == "eye-in-hand" else X_true @ Cm @ invert(Z_true)
        G_true.append(G)
        w = rng.normal(0.0, np.radians(noise.sigma_deg), 3)
        v = rng.normal(0.0, noise.sigma_mm * 1e-3, 3)
        G_rec.append(perturb(G, np.concatenate([w, v])))
        uv = camera.project(tp.xyz_m @ Cm[:3, :3].T + Cm[:3, 3]) + rng.normal(0.0, pixel_sigma_px, (len(tp.ids), 2))
        dets.append(Detection(f"view{k:02d}.png", True, tp.ids.copy(), uv, image_size=camera.size))
    return SimulatedHandEye(setup, camera, target, X_true, Z_true, G_true, G_rec, Cs, dets)
