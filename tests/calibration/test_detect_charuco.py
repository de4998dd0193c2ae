"""ChArUco detection through OpenCV: full and partial boards, OpenCV's corner ids."""

from __future__ import annotations

import numpy as np

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.targets import Charuco
from tests.calibration.conftest import plate_pose, render_target, truth_uv

BOARD = Charuco(8, 6, 25.0, 18.0, "DICT_5X5_100")


def test_full_board_rotated(camera: CameraModel) -> None:
    T = plate_pose(BOARD, 0.4, 30, tilt_dir_deg=10, roll_deg=160)
    det = detect(render_target(camera, BOARD, T, seed=4), BOARD)
    assert det.found, det.reason
    assert det.ids.tolist() == list(range(35))
    assert np.hypot(*(det.uv - truth_uv(camera, BOARD, T)[det.ids]).T).max() < 0.3


def test_partial_board(camera: CameraModel) -> None:
    T = plate_pose(BOARD, 0.3, 10, shift_m=(0.09, 0.0))  # the right part of the board leaves the image
    truth = truth_uv(camera, BOARD, T)
    det = detect(render_target(camera, BOARD, T, seed=5), BOARD)
    assert det.found, det.reason
    assert 4 <= len(det.ids) < 35
    inside = (truth[:, 0] > 0) & (truth[:, 0] < camera.width - 1)
    assert set(det.ids.tolist()) <= set(np.nonzero(inside)[0].tolist())
    assert np.hypot(*(det.uv - truth[det.ids]).T).max() < 0.3


def test_wrong_dictionary_is_not_found(camera: CameraModel) -> None:
    T = plate_pose(BOARD, 0.4, 10)
    img = render_target(camera, BOARD, T)
    det = detect(img, Charuco(8, 6, 25.0, 18.0, "DICT_4X4_50"))
    assert not det.found
    assert "DICT_4X4_50" in det.reason
