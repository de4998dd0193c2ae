"""Circle grids through OpenCV's findCirclesGrid, with our id convention and bias correction."""

from __future__ import annotations

import numpy as np

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.targets import CircleGrid
from tests.calibration.conftest import plate_pose, render_target, truth_uv


def test_asymmetric_grid_rotated(camera: CameraModel) -> None:
    grid = CircleGrid(4, 11, 12.0, 8.0, asymmetric=True)
    for roll in (0, 170):
        T = plate_pose(grid, 0.35, 30, tilt_dir_deg=70, roll_deg=roll)
        det = detect(render_target(camera, grid, T, seed=roll), grid)
        assert det.found, det.reason
        assert det.ids.tolist() == list(range(44))
        assert np.hypot(*(det.uv - truth_uv(camera, grid, T)[det.ids]).T).max() < 0.1


def test_symmetric_grid_up_to_its_half_turn(camera: CameraModel) -> None:
    grid = CircleGrid(7, 6, 20.0, 10.0)
    T = plate_pose(grid, 0.45, 35, tilt_dir_deg=30, roll_deg=190)
    det = detect(render_target(camera, grid, T, seed=2), grid)
    assert det.found, det.reason
    truth = truth_uv(camera, grid, T)
    assert min(np.abs(det.uv - truth).max(), np.abs(det.uv - truth[::-1]).max()) < 0.1
    assert det.uv_ellipse is not None


def test_wrong_size_is_not_found(camera: CameraModel) -> None:
    grid = CircleGrid(7, 6, 20.0, 10.0)
    T = plate_pose(grid, 0.45, 10)
    det = detect(render_target(camera, grid, T), CircleGrid(6, 6, 20.0, 10.0))
    assert not det.found
    assert "circle grid" in det.reason
