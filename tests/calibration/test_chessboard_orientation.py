"""Chessboard ids follow the board even when the square outside corner (0, 0) is out of the image.

Regression: the orientation cue used to sample only that outer square; with it off-image the
half-turned grid won (found on rendered 11x8 views near the image border).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.targets import Chessboard
from drivers.sim.imaging import Imaging, PlanarObject, render

K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 480.0], [0.0, 0.0, 1.0]])
CAM = CameraModel("opencv5", 1280, 960, K, np.zeros(5))


@pytest.mark.parametrize("spin_deg", [0.0, 180.0, 90.0, -90.0])
def test_ids_follow_the_board_with_corner_zero_near_the_border(spin_deg: float) -> None:
    board = Chessboard(11, 8, 25.0)
    s = board.square_m
    centre = np.array([5 * s, 3.5 * s, 0.0])
    R = g.rotvec_to_matrix([0.0, 0.0, np.radians(spin_deg)]) @ g.rotvec_to_matrix([0.15, -0.1, 0.0])
    T = g.make_transform(R, -R @ centre + np.array([0.0, 0.0, 0.55]))
    # Shift the board so that its corner (0, 0) sits 0.45 squares inside the image border.
    uv0 = CAM.project(g.transform_points(T, [[0.0, 0.0, 0.0]]))[0]
    px_per_square = 1400 * s / 0.55
    target_uv = np.where(uv0 < [640, 480], 0.45 * px_per_square, [1279 - 0.45 * px_per_square,
                                                                  959 - 0.45 * px_per_square])
    axis = np.argmin(np.minimum(uv0, [1279, 959] - uv0))
    shift = np.zeros(3)
    shift[axis] = (target_uv[axis] - uv0[axis]) * 0.55 / 1400
    T[:3, 3] += shift
    truth = CAM.project(g.transform_points(T, board.points().xyz_m))
    assert np.all((truth > 0) & (truth < [1279, 959]))
    img = render(CAM, [PlanarObject(T, board.reflectance)], Imaging(blur_sigma_px=0.7, noise_sigma=1.0),
                 np.random.default_rng(3))
    det = detect(img, board, "edge")
    assert det.found, det.reason
    err = np.linalg.norm(det.uv - truth[det.ids], axis=1)
    assert err.max() < 0.3, f"ids do not follow the board (max error {err.max():.1f} px)"
