"""Shared helpers for the calibration tests: render a target seen by a camera, with its truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import invert, make_transform, quaternion_to_matrix, rotvec_to_matrix, transform_points
from calibration.observations import Detection
from calibration.targets import Chessboard, PlanarTarget
from drivers.sim.imaging import Imaging, PlanarObject, render

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


ETH_ARM = DATA / "handeye_ethz_robot_arm_sr300"
SR300_IR = CameraModel("opencv5", 640, 480, np.array([[471.845, 0, 316.85], [0, 471.686, 237.389], [0, 0, 1]]),
                       np.array([-0.15024, -0.00326, -0.00126, -0.00042, 0.0]))
"""The ETH set's SR300 infrared camera (``sr300_ir.yaml``)."""


def eth_arm_stations(step: int = 100) -> tuple[list[NDArray[np.float64]], NDArray[np.float64], list[Detection],
                                                Chessboard]:
    """ETH ASL robot arm + SR300 (real, tests/data), every ``step``-th measured camera pose: the
    robot poses (nearest 50 Hz sample at the published time offset), the camera pose rows, and
    virtual detections of a 6x6 grid (pitch 40 mm) seen through ``SR300_IR``."""
    rob = np.loadtxt(ETH_ARM / "robot_arm_complete_bag_color_and_ir_base_link_sr300_hinge.csv", delimiter=",")
    cam = np.loadtxt(ETH_ARM / "robot_arm_complete_bag_color_and_ir_target_ir.csv", delimiter=",")[::step]
    cam = cam[(cam[:, 0] - 0.02 > rob[0, 0]) & (cam[:, 0] - 0.02 < rob[-1, 0])]
    G = []
    for t in cam[:, 0] - 0.02:
        r = rob[np.argmin(np.abs(rob[:, 0] - t))]
        G.append(make_transform(quaternion_to_matrix(r[4:8]), r[1:4]))
    grid = Chessboard(6, 6, 40.0)
    tp = grid.points()
    dets = []
    for k, row in enumerate(cam):
        C = invert(make_transform(quaternion_to_matrix(row[4:8]), row[1:4]))
        dets.append(Detection(f"t{k:03d}", True, tp.ids.copy(), SR300_IR.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3])))
    return G, cam, dets, grid
