"""Chessboard detection: rendered boards (ids in the target frame) and the real Udacity photo sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import detect, detect_file
from calibration.targets import Chessboard
from tests.calibration.conftest import DATA, plate_pose, render_target, truth_uv


@pytest.mark.parametrize("roll_deg", [0, 120, 200, 290])
def test_asymmetric_board_ids_follow_the_board(camera: CameraModel, roll_deg: float) -> None:
    """9x6: cols + rows odd, so the half turn is read from the square colours."""
    board = Chessboard(9, 6, 20.0)
    T = plate_pose(board, 0.45, 30, tilt_dir_deg=40, roll_deg=roll_deg)
    det = detect(render_target(camera, board, T, noise=2.0, blur=0.7, seed=int(roll_deg)), board)
    assert det.found, det.reason
    assert det.ids.tolist() == list(range(54))
    assert np.hypot(*(det.uv - truth_uv(camera, board, T)[det.ids]).T).max() < 0.15


@pytest.mark.parametrize("roll_deg", [10, 200])
def test_symmetric_board_up_to_its_half_turn(camera: CameraModel, roll_deg: float) -> None:
    """8x6 looks the same after a half turn: the result is the truth or its half turn, with x rightwards."""
    board = Chessboard(8, 6, 20.0)
    T = plate_pose(board, 0.45, 25, tilt_dir_deg=-30, roll_deg=roll_deg)
    det = detect(render_target(camera, board, T, seed=1), board)
    assert det.found, det.reason
    truth = truth_uv(camera, board, T)
    err = min(np.abs(det.uv - truth).max(), np.abs(det.uv - truth[::-1]).max())
    assert err < 0.15
    G = det.uv.reshape(6, 8, 2)
    assert G[0, -1, 0] > G[0, 0, 0]  # convention: the x axis points rightwards on screen


def _found(folder: str, cols: int, rows: int, skip: tuple[str, ...] = ()) -> dict[str, tuple[bool, str]]:
    board = Chessboard(cols, rows, 1.0)
    out = {}
    for p in sorted((DATA / folder).glob("*.jpg")):
        if p.name in skip:
            continue
        det = detect_file(p, board)
        out[p.name] = (det.found, det.reason)
        if det.found:
            assert len(det.ids) == cols * rows
    return out


def test_udacity_camera_cal_9x6() -> None:
    res = _found("udacity_camera_cal_9x6", 9, 6)
    assert len(res) == 20
    missing = sorted(k for k, (ok, _) in res.items() if not ok)
    assert missing == ["calibration1.jpg", "calibration4.jpg", "calibration5.jpg"]
    assert "cropped" in res["calibration4.jpg"][1]
    assert all(res[k][1] for k in missing)


def test_udacity_gopro_wide_8x6() -> None:
    # test_image.jpg is the notebook's undistortion test image, not a calibration view
    res = _found("udacity_gopro_wide_8x6", 8, 6, skip=("test_image.jpg",))
    assert len(res) == 36
    missing = sorted(k for k, (ok, _) in res.items() if not ok)
    assert missing == ["GOPR0055.jpg"]
    assert res["GOPR0055.jpg"][1]


def test_data_folder_is_where_the_readme_says() -> None:
    assert Path(DATA / "udacity_camera_cal_9x6" / "SOURCE.txt").is_file()
