"""4-DOF hand-eye on a virtual SCARA-style cell: truth within the reported uncertainty, the target
height fixing what the motion cannot see, pixels mapped like a 6-DOF result, clear refusals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform
from calibration.handeye import HandEyeError, RobotNoise, calibrate_handeye_dof4
from calibration.measure import pixel_to_robot
from calibration.synthetic import ScaraSet, simulate_scara
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(7, 5, 25.0)
NOISE = RobotNoise(0.02, 0.01)


def _solve(s: ScaraSet, z_mm: float | None = None) -> dict:
    return calibrate_handeye_dof4(s.setup, s.G_recorded, s.detections, CAM, BOARD,
                                  s.target_z_mm if z_mm is None else z_mm, NOISE, leave_one_out=False).to_json()


def _x(out: dict, setup: str) -> np.ndarray:
    return np.array(out["T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"])


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_truth_within_reported_uncertainty(setup: str) -> None:
    d2 = []
    for seed in range(3):
        s = simulate_scara(setup, 12, np.random.default_rng(seed), camera=CAM, target=BOARD, robot_noise=NOISE)
        out = _solve(s)
        assert out["dof"] == 4 and out["setup"] == setup and out["verdict"]["ok"]
        X = _x(out, setup)
        w = Rotation.from_matrix(s.X_true[:3, :3] @ X[:3, :3].T).as_rotvec()
        e = np.concatenate([w, s.X_true[:3, 3] - X[:3, 3]])
        cov = np.array(out["uncertainty"]["covariance"])
        d2.append(float(e @ np.linalg.solve(cov, e)))
        assert np.degrees(np.linalg.norm(w)) <= 3.0 * out["uncertainty"]["rot_deg"]
        assert 1e3 * np.linalg.norm(e[3:]) <= 3.0 * out["uncertainty"]["trans_mm"]
    assert np.mean(d2) < 20.0  # chi2 with 6 dof: mean 6


def test_target_height_fixes_the_unseen_direction() -> None:
    """A height stated 2 mm too high moves the camera 2 mm along the tool z axis and nothing else."""
    s = simulate_scara("eye-in-hand", 10, np.random.default_rng(5), camera=CAM, target=BOARD, robot_noise=NOISE)
    a, b = _solve(s), _solve(s, s.target_z_mm + 2.0)
    d = (_x(b, "eye-in-hand") - _x(a, "eye-in-hand"))[:3, 3] * 1e3
    tool_z = np.array(a["fixed_by_constraint"]["unseen_direction_X"])
    assert d @ tool_z == pytest.approx(2.0, abs=0.01)
    assert np.linalg.norm(d - (d @ tool_z) * tool_z) < 0.01
    assert b["T_base_target"][2][3] * 1e3 == pytest.approx(s.target_z_mm + 2.0, abs=1e-9)
    fixed = a["fixed_by_constraint"]
    assert fixed["target_z_mm"] == s.target_z_mm and "tool z axis" in fixed["fixed"][0]


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_maps_pixels_like_the_true_calibration(setup: str) -> None:
    """``pixel_to_robot`` takes the 4-DOF he.json as it is; mapped points as good as the truth's (1.5x)."""
    s = simulate_scara(setup, 14, np.random.default_rng(11), camera=CAM, target=BOARD, robot_noise=NOISE)
    out = _solve(s)
    truth = dict(out)
    truth["T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"] = s.X_true.tolist()
    e_est, e_true = [], []
    for G, det, P in zip(s.G_recorded, s.detections, s.points_base_true, strict=True):
        pose = G if setup == "eye-in-hand" else None
        for j in range(0, len(P), 4):
            a = pixel_to_robot(out, det.uv[j], plane_z_mm=P[j, 2] * 1e3, robot_pose=pose)
            b = pixel_to_robot(truth, det.uv[j], plane_z_mm=P[j, 2] * 1e3, robot_pose=pose)
            e_est.append(np.linalg.norm(a.xyz_mm[:2] - P[j, :2] * 1e3))
            e_true.append(np.linalg.norm(b.xyz_mm[:2] - P[j, :2] * 1e3))
            assert np.all(a.sigma_mm[:2] > 0)
    ratio = np.sqrt(np.mean(np.square(e_est))) / np.sqrt(np.mean(np.square(e_true)))
    assert ratio <= (1.5 if setup == "eye-in-hand" else 2.0), ratio


def test_refusals_say_why() -> None:
    s = simulate_scara("eye-in-hand", 8, np.random.default_rng(2), camera=CAM, target=BOARD, robot_noise=NOISE)
    tilted = list(s.G_recorded)
    tilted[3] = make_transform(Rotation.from_rotvec([0.1, 0, 0]).as_matrix() @ tilted[3][:3, :3], tilted[3][:3, 3])
    with pytest.raises(HandEyeError, match="station 3's tool z axis is tilted 5.7.*need the 6-DOF solver") as tilt:
        calibrate_handeye_dof4("eye-in-hand", tilted, s.detections, CAM, BOARD, s.target_z_mm, NOISE)
    assert tilt.value.alternative == "dof6"  # the front ends word the way there (cellctl/hints.py)
    with pytest.raises(HandEyeError, match="at least 3 stations"):
        calibrate_handeye_dof4("eye-in-hand", s.G_recorded[:2], s.detections[:2], CAM, BOARD, 12.0, NOISE)
    with pytest.raises(HandEyeError, match="finite height"):
        calibrate_handeye_dof4("eye-in-hand", s.G_recorded, s.detections, CAM, BOARD, float("nan"), NOISE)
    same = [make_transform(s.G_recorded[0][:3, :3], g[:3, 3]) for g in s.G_recorded]
    with pytest.raises(HandEyeError, match="turns only 0.0 deg"):
        calibrate_handeye_dof4("eye-in-hand", same, s.detections, CAM, BOARD, s.target_z_mm, NOISE)


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_tool_pointing_up_like_a_scara(setup: str) -> None:
    """The tool z axis may point up (a SCARA's) as well as down (a UR picking top-down)."""
    s = simulate_scara(setup, 10, np.random.default_rng(7), camera=CAM, target=BOARD, robot_noise=NOISE,
                       tool_down=False)
    out = _solve(s)
    X = _x(out, setup)
    rot = np.degrees(np.linalg.norm(Rotation.from_matrix(s.X_true[:3, :3] @ X[:3, :3].T).as_rotvec()))
    assert rot <= 3.0 * out["uncertainty"]["rot_deg"]
    assert 1e3 * np.linalg.norm(X[:3, 3] - s.X_true[:3, 3]) <= 3.0 * out["uncertainty"]["trans_mm"]
    assert out["motion"]["tool_z_axis_base"][2] == pytest.approx(1.0, abs=1e-3)
