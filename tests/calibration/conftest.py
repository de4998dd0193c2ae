"""Shared helpers for the calibration tests: render a target seen by a camera, with its truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform, rotvec_to_matrix, transform_points
from calibration.render import Imaging, PlanarObject, render
from calibration.targets import PlanarTarget

DATA = Path(__file__).resolve().parents[1] / "data"


def plate_pose(target: PlanarTarget, distance_m: float, tilt_deg: float = 0.0, tilt_dir_deg: float = 0.0,
               roll_deg: float = 0.0, shift_m: tuple[float, float] = (0.0, 0.0)) -> NDArray[np.float64]:
    """``T_cam_target`` with the plate's centre ``distance_m`` ahead, tilted and rolled."""
    x0, y0, x1, y1 = target.extent_m()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    axis = np.array([np.cos(np.deg2rad(tilt_dir_deg)), np.sin(np.deg2rad(tilt_dir_deg)), 0.0])
    R = rotvec_to_matrix([0.0, 0.0, np.deg2rad(roll_deg)]) @ rotvec_to_matrix(np.deg2rad(tilt_deg) * axis)
    return make_transform(R, np.array([shift_m[0], shift_m[1], distance_m]) - R @ centre)


def render_target(camera: CameraModel, target: PlanarTarget, T_cam_target: NDArray[np.float64],
                  noise: float = 1.0, blur: float = 0.7, light_gradient: float = 0.0, seed: int = 0
                  ) -> NDArray[np.uint8]:
    imaging = Imaging(noise_sigma=noise, blur_sigma_px=blur, light_gradient=light_gradient)
    return render(camera, [PlanarObject(T_cam_target, target.reflectance)], imaging,
                  np.random.default_rng(seed), supersample=4)


def truth_uv(camera: CameraModel, target: PlanarTarget, T_cam_target: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 2) true image of every target point, indexed by id order of ``target.points()``."""
    return camera.project(transform_points(T_cam_target, target.points().xyz_m))


@pytest.fixture(scope="session")
def camera() -> CameraModel:
    """A 800x600 camera with mild barrel distortion."""
    K = np.array([[900.0, 0.0, 401.0], [0.0, 900.0, 297.0], [0.0, 0.0, 1.0]])
    return CameraModel("opencv5", 800, 600, K, np.array([-0.12, 0.08, 0.0005, -0.0003, 0.0]))
