"""Hand-eye from a measured target frame: truth within the reported uncertainty from 3 stations
(and from one), a check of an AX=XB result that tells agreement from a wrong result, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import PoseError, make_transform
from calibration.handeye import HandEyeError, RobotNoise, calibrate_handeye, calibrate_handeye_measured, compare_handeye
from calibration.synthetic import perturb_pose, simulate_handeye
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 957], [0, 1900, 604], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 25.0)
NOISE = RobotNoise(0.03, 0.005)


def _error(X: np.ndarray, X_true: np.ndarray) -> np.ndarray:
    w = Rotation.from_matrix(X_true[:3, :3] @ X[:3, :3].T).as_rotvec()
    return np.concatenate([w, X_true[:3, 3] - X[:3, 3]])


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_three_stations_truth_within_reported_uncertainty(setup: str) -> None:
    d2 = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        s = simulate_handeye(setup, 3, rng, camera=CAM, target=BOARD, robot_noise=NOISE)
        Z_measured = perturb_pose(s.Z_true, rng, NOISE)  # the tracker's noise
        res = calibrate_handeye_measured(setup, s.G_recorded, s.detections, CAM, BOARD, Z_measured, NOISE, NOISE)
        e = _error(res.X, s.X_true)
        d2.append(float(e @ np.linalg.solve(res.cov_X, e)))
        out = res.to_json()
        assert out["stations"] == 3 and out["method"] == "measured_frame"
        assert np.degrees(np.linalg.norm(e[:3])) <= max(0.03, 3 * out["uncertainty"]["rot_deg"])
        assert 1e3 * np.linalg.norm(e[3:]) <= max(0.2, 3 * out["uncertainty"]["trans_mm"])
    assert 1.0 < np.mean(d2) < 18.0, d2  # chi2 with 6 dof: mean 6


def test_one_station_is_enough() -> None:
    rng = np.random.default_rng(9)
    s = simulate_handeye("eye-in-hand", 1, rng, camera=CAM, target=BOARD, robot_noise=NOISE)
    res = calibrate_handeye_measured("eye-in-hand", s.G_recorded, s.detections, CAM, BOARD,
                                     perturb_pose(s.Z_true, rng, NOISE), NOISE, NOISE)
    e = _error(res.X, s.X_true)
    assert 1e3 * np.linalg.norm(e[3:]) <= 4 * res.to_json()["uncertainty"]["trans_mm"]
    assert np.degrees(np.linalg.norm(e[:3])) <= 4 * res.to_json()["uncertainty"]["rot_deg"]


def test_check_of_an_axxb_result() -> None:
    rng = np.random.default_rng(4)
    s = simulate_handeye("eye-in-hand", 10, rng, camera=CAM, target=BOARD, robot_noise=NOISE)
    he = calibrate_handeye("eye-in-hand", s.G_recorded, s.detections, CAM, BOARD, NOISE, leave_one_out=False).to_json()
    measured = calibrate_handeye_measured("eye-in-hand", s.G_recorded[:3], s.detections[:3], CAM, BOARD,
                                          perturb_pose(s.Z_true, rng, NOISE), NOISE, NOISE)
    good = compare_handeye(he, measured)
    assert good["trans_sigmas"] < 4.0 and good["trans_mm"] < 0.3
    wrong = dict(he)
    T = np.array(he["T_tool_cam"])
    wrong["T_tool_cam"] = make_transform(T[:3, :3], T[:3, 3] + [0.002, 0.0, 0.0]).tolist()
    bad = compare_handeye(wrong, measured)
    assert bad["trans_mm"] == pytest.approx(2.0, abs=0.3) and bad["trans_sigmas"] > 8.0
    with pytest.raises(HandEyeError, match="eye-in-hand he.json with T_tool_cam"):
        compare_handeye({"setup": "eye-to-hand", "T_base_cam": T.tolist()}, measured)


def test_bad_input() -> None:
    s = simulate_handeye("eye-to-hand", 2, np.random.default_rng(1), camera=CAM, target=BOARD, robot_noise=NOISE)
    bad = np.array(s.Z_true)
    bad[:3, :3] *= 2.0
    with pytest.raises(PoseError, match="measured T_tool_target rotation block is not a proper rotation"):
        calibrate_handeye_measured("eye-to-hand", s.G_recorded, s.detections, CAM, BOARD, bad)
    with pytest.raises(HandEyeError, match="setup must be one of"):
        calibrate_handeye_measured("on-the-table", s.G_recorded, s.detections, CAM, BOARD, s.Z_true)
    for d in s.detections:
        d.found = False
    with pytest.raises(HandEyeError, match="needs at least one image"):
        calibrate_handeye_measured("eye-to-hand", s.G_recorded, s.detections, CAM, BOARD, s.Z_true)
