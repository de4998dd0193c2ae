"""Pose from one view: exact on exact data, covariance consistent with the scatter."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, look_at, transform_error
from calibration.pose import PoseEstimationError, estimate_pose
from calibration.targets import Chessboard

CAM = CameraModel("division", 1280, 960, np.array([[1100.0, 0, 640], [0, 1100, 480], [0, 0, 1]]),
                  np.array([-0.3]))
BOARD = Chessboard(9, 6, 30.0)


def _pose(tilt: float) -> np.ndarray:
    return invert(look_at([0.1 + tilt, -0.05, -0.7], [0.12, 0.075, 0.0], up=[0, -1, 0]))


@pytest.mark.parametrize("tilt", [0.0, 0.3])
def test_exact_pose_planar(tilt: float) -> None:
    T = _pose(tilt)
    X = BOARD.points().xyz_m
    uv = CAM.project(X @ T[:3, :3].T + T[:3, 3])
    res = estimate_pose(CAM, X, uv)
    rot, trans = transform_error(res.T_cam_target, T)
    assert rot < 1e-8 and trans < 1e-9
    assert res.rms_px < 1e-6


def test_covariance_matches_scatter() -> None:
    T = _pose(0.2)
    X = BOARD.points().xyz_m
    uv0 = CAM.project(X @ T[:3, :3].T + T[:3, 3])
    rng = np.random.default_rng(1)
    errs, sig = [], []
    for _ in range(40):
        res = estimate_pose(CAM, X, uv0 + rng.normal(0, 0.5, uv0.shape))
        errs.append(np.linalg.norm(res.T_cam_target[:3, 3] - T[:3, 3]) * 1e3)
        sig.append(res.sigma_trans_mm)
    ratio = np.sqrt(np.mean(np.square(errs))) / np.mean(sig)
    assert 0.6 < ratio < 1.6
    out = res.to_json()
    assert np.asarray(out["covariance"]).shape == (6, 6) and out["uncertainty"]["trans_mm"] > 0


def test_non_planar_points() -> None:
    rng = np.random.default_rng(2)
    X = rng.uniform(-0.1, 0.1, (12, 3))
    T = _pose(0.1)
    uv = CAM.project(X @ T[:3, :3].T + T[:3, 3])
    res = estimate_pose(CAM, X, uv)
    assert transform_error(res.T_cam_target, T)[1] < 1e-8


def test_degenerate_inputs() -> None:
    X = BOARD.points().xyz_m
    with pytest.raises(PoseEstimationError, match="at least 4"):
        estimate_pose(CAM, X[:3], np.zeros((3, 2)))
    with pytest.raises(PoseEstimationError, match="target points but"):
        estimate_pose(CAM, X[:6], np.zeros((5, 2)))
    line = X[:9]  # first row: collinear
    with pytest.raises(PoseEstimationError, match="collinear"):
        estimate_pose(CAM, line, np.zeros((9, 2)) + 500)
