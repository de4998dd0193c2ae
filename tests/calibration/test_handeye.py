"""Hand-eye: truth within the reported uncertainty, convention mistakes named, degenerate motion refused."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import invert, make_transform, rotvec_to_matrix, transform_to_ur_pose, ur_pose_to_transform
from calibration.handeye import ConventionError, HandEyeError, RobotNoise, calibrate_handeye, transform_error_deg_mm
from calibration.observations import Detection
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
TARGET = Chessboard(8, 6, 30.0)
NOISE = RobotNoise(sigma_mm=0.05, sigma_deg=0.01)


def _sim(setup: str, seed: int, n: int = 10):
    return simulate_handeye(setup, n, np.random.default_rng(seed), camera=CAM, target=TARGET,
                            robot_noise=NOISE, pixel_sigma_px=0.05)


def _detections_for(setup: str, G: list[np.ndarray], X: np.ndarray, Z: np.ndarray, rng: np.random.Generator):
    tp = TARGET.points()
    dets = []
    for k, g in enumerate(G):
        C = invert(X) @ invert(g if setup == "eye-in-hand" else invert(g)) @ Z
        uv = CAM.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3]) + rng.normal(0, 0.05, (len(tp.ids), 2))
        assert np.all((uv > 0) & (uv < [CAM.width, CAM.height])), "test geometry: target left the image"
        dets.append(Detection(f"v{k:02d}.png", True, tp.ids.copy(), uv, image_size=CAM.size))
    return dets


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_truth_within_reported_uncertainty(setup: str) -> None:
    sim = _sim(setup, seed=3)
    res = calibrate_handeye(setup, sim.G_recorded, sim.detections, CAM, TARGET, NOISE)
    rot_deg, trans_mm = transform_error_deg_mm(res.X, sim.X_true)
    # 3-sigma in the RMS sense (3 dof each): the error is a single draw of the reported distribution
    assert rot_deg < 3.0 * res.uncertainty_rot_deg
    assert trans_mm < 3.0 * res.uncertainty_trans_mm
    # and the reported uncertainty is not uselessly large: sub-millimetre for this UR-class noise
    assert res.uncertainty_trans_mm < 0.5 and res.uncertainty_rot_deg < 0.05
    assert res.rms_px < 0.2
    assert 0.5 < res.chi2_reduced < 2.0
    js = res.to_json()
    names = ("T_tool_cam", "T_base_target") if setup == "eye-in-hand" else ("T_base_cam", "T_tool_target")
    for key in (*names, "rms_px", "rot_deg", "trans_mm", "uncertainty", "poses", "leave_one_out"):
        assert key in js
    assert js["setup"] == setup
    assert js["uncertainty"]["trans_mm"] == pytest.approx(res.uncertainty_trans_mm)
    assert len(js["poses"]) == 10 and all("loo_mm" in p and "rms_px" in p for p in js["poses"])
    # leave-one-out prediction is at the level of the robot noise, not millimetres
    assert js["leave_one_out"]["position_mm"]["rms"] < 1.0
    assert js["verdict"]["ok"]


def test_joint_refinement_beats_treating_the_robot_as_exact() -> None:
    """The robot-noise prior is what makes it ML: with an (almost) exact-robot prior it gets worse."""
    errs_ml, errs_exact = [], []
    for seed in (11, 12):
        sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(seed), camera=CAM, target=TARGET,
                               robot_noise=RobotNoise(0.1, 0.02), pixel_sigma_px=0.03)
        ml = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET, RobotNoise(0.1, 0.02),
                               leave_one_out=False)
        exact = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET,
                                  RobotNoise(1e-4, 2e-5), leave_one_out=False)
        errs_ml.append(transform_error_deg_mm(ml.X, sim.X_true)[1])
        errs_exact.append(transform_error_deg_mm(exact.X, sim.X_true)[1])
    assert np.mean(errs_ml) < np.mean(errs_exact)


def test_inverted_poses_named() -> None:
    sim = _sim("eye-in-hand", seed=4)
    with pytest.raises(ConventionError, match="inverted"):
        calibrate_handeye("eye-in-hand", [invert(g) for g in sim.G_recorded], sim.detections, CAM, TARGET, NOISE)


def test_wrong_setup_looks_like_inverted_poses_and_says_so() -> None:
    sim = _sim("eye-in-hand", seed=5)
    with pytest.raises(ConventionError, match="setup"):
        calibrate_handeye("eye-to-hand", sim.G_recorded, sim.detections, CAM, TARGET, NOISE)


def test_millimetres_named() -> None:
    sim = _sim("eye-to-hand", seed=6)
    raw = np.array([transform_to_ur_pose(g) for g in sim.G_recorded])
    raw[:, :3] *= 1000.0
    G_mm = [ur_pose_to_transform(r) for r in raw]
    with pytest.raises(ConventionError, match="millimetres"):
        calibrate_handeye("eye-to-hand", G_mm, sim.detections, CAM, TARGET, NOISE, raw_ur_poses=raw)


def test_euler_angles_named() -> None:
    sim = _sim("eye-in-hand", seed=7)
    raw = np.array([np.concatenate([g[:3, 3], Rotation.from_matrix(g[:3, :3]).as_euler("xyz")])
                    for g in sim.G_recorded])
    G_wrong = [ur_pose_to_transform(r) for r in raw]  # the file's Euler angles parsed as a rotation vector
    with pytest.raises(ConventionError, match="Euler") as info:
        calibrate_handeye("eye-in-hand", G_wrong, sim.detections, CAM, TARGET, NOISE, raw_ur_poses=raw)
    assert "rpy2rotvec" in str(info.value)


def test_pure_translation_refused() -> None:
    sim = _sim("eye-in-hand", seed=8)
    rng = np.random.default_rng(8)
    G0 = sim.G_true[0]
    G = [G0 @ make_transform(np.eye(3), rng.uniform(-0.03, 0.03, 3)) for _ in range(8)]
    dets = _detections_for("eye-in-hand", G, sim.X_true, sim.Z_true, rng)
    with pytest.raises(HandEyeError, match="only by translation"):
        calibrate_handeye("eye-in-hand", G, dets, CAM, TARGET, NOISE)


def test_rotation_about_one_axis_refused() -> None:
    sim = _sim("eye-in-hand", seed=9)
    rng = np.random.default_rng(9)
    G0 = sim.G_true[0]
    axis = invert(sim.X_true)[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the camera's optical axis, in the tool frame
    G = [G0 @ make_transform(rotvec_to_matrix(axis * np.radians(a)), rng.uniform(-0.01, 0.01, 3))
         for a in (-30, -18, -6, 6, 18, 30, 40, -40)]
    dets = _detections_for("eye-in-hand", G, sim.X_true, sim.Z_true, rng)
    with pytest.raises(HandEyeError, match="one axis"):
        calibrate_handeye("eye-in-hand", G, dets, CAM, TARGET, NOISE)


def test_top_down_only_motion_refused_with_pointer_to_4dof() -> None:
    """A SCARA-style set (the tool turns only about the base z axis) is degenerate for 6-DOF AX=XB;
    the refusal names the 4-DOF solver."""
    sim = _sim("eye-in-hand", seed=12)
    rng = np.random.default_rng(12)
    G0 = sim.G_true[7]  # a view with the target well inside the image
    centre = make_transform(np.eye(3), (sim.Z_true @ np.append(TARGET.points().xyz_m.mean(axis=0), 1.0))[:3])
    G = [centre @ make_transform(rotvec_to_matrix([0.0, 0.0, np.radians(a)]), np.append(rng.uniform(-0.01, 0.01, 2), 0))
         @ invert(centre) @ G0 for a in (-12, -8, -4, 0, 4, 8, 12, 15)]
    dets = _detections_for("eye-in-hand", G, sim.X_true, sim.Z_true, rng)
    with pytest.raises(HandEyeError, match="one axis") as err:
        calibrate_handeye("eye-in-hand", G, dets, CAM, TARGET, NOISE)
    assert err.value.alternative == "dof4" and "--" not in str(err.value)  # a front end words the way there


def test_too_few_poses_refused() -> None:
    sim = _sim("eye-in-hand", seed=10, n=2)
    with pytest.raises(HandEyeError, match="at least 3"):
        calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET, NOISE)


def test_mismatched_counts_refused() -> None:
    sim = _sim("eye-in-hand", seed=10, n=5)
    with pytest.raises(HandEyeError, match="each image needs"):
        calibrate_handeye("eye-in-hand", sim.G_recorded[:4], sim.detections, CAM, TARGET, NOISE)


def test_image_paired_with_wrong_pose_reported_and_left_out() -> None:
    sim = _sim("eye-to-hand", seed=13, n=12)
    G = list(sim.G_recorded)
    G[4] = G[9]  # a duplicated row: image 4 now carries the pose of image 9
    res = calibrate_handeye("eye-to-hand", G, sim.detections, CAM, TARGET, NOISE, leave_one_out=False)
    outl = [p for p in res.problems if p.code == "pose_outlier"]
    assert outl and "view04.png" in outl[0].message
    assert len(res.stations) == 11
    rot_deg, trans_mm = transform_error_deg_mm(res.X, sim.X_true)
    assert trans_mm < 3.0 * res.uncertainty_trans_mm and rot_deg < 3.0 * res.uncertainty_rot_deg


def test_small_and_near_180_rotation_pairs_dropped_and_reported() -> None:
    sim = _sim("eye-in-hand", seed=14, n=9)
    rng = np.random.default_rng(14)
    near = sim.G_true[0] @ make_transform(rotvec_to_matrix([0.0, 0.01, 0.0]), [0.0, 0, 0])
    # a half turn (175 deg) of the camera about the line from it to the target's centre
    C0 = sim.C_true[0]
    centre_cam = C0[:3, :3] @ TARGET.points().xyz_m.mean(axis=0) + C0[:3, 3]
    axis_cam = centre_cam / np.linalg.norm(centre_cam)
    spin = make_transform(rotvec_to_matrix(axis_cam * np.radians(175.0)), np.zeros(3))
    about = make_transform(np.eye(3), centre_cam) @ spin @ make_transform(np.eye(3), -centre_cam)
    half = sim.G_true[0] @ sim.X_true @ about @ invert(sim.X_true)
    extra = _detections_for("eye-in-hand", [near, half], sim.X_true, sim.Z_true, rng)
    extra[0].image, extra[1].image = "near_duplicate.png", "half_turn.png"
    res = calibrate_handeye("eye-in-hand", [*sim.G_recorded, near, half], [*sim.detections, *extra], CAM, TARGET,
                            NOISE, leave_one_out=False)
    dropped = [p for p in res.problems if p.code == "pairs_dropped"]
    assert dropped and "dropped" in dropped[0].message and "near 180" in dropped[0].message
    assert res.pairs["dropped_small"] >= 1 and res.pairs["dropped_near_180"] >= 1
    rot_deg, trans_mm = transform_error_deg_mm(res.X, sim.X_true)
    assert trans_mm < 3.0 * res.uncertainty_trans_mm and rot_deg < 3.0 * res.uncertainty_rot_deg


def test_robot_noise_estimated_from_data() -> None:
    true = RobotNoise(0.3, 0.05)
    sim = simulate_handeye("eye-to-hand", 15, np.random.default_rng(15), camera=CAM, target=TARGET, robot_noise=true,
                           pixel_sigma_px=0.05)
    res = calibrate_handeye("eye-to-hand", sim.G_recorded, sim.detections, CAM, TARGET, NOISE, leave_one_out=False,
                            estimate_robot_noise=True)
    assert 0.5 * true.sigma_mm < res.robot_noise.sigma_mm < 2.0 * true.sigma_mm
    assert 0.5 * true.sigma_deg < res.robot_noise.sigma_deg < 2.0 * true.sigma_deg
    assert any(p.code == "robot_noise_estimated" for p in res.problems)
    rot_deg, trans_mm = transform_error_deg_mm(res.X, sim.X_true)
    assert trans_mm < 3.0 * res.uncertainty_trans_mm and rot_deg < 3.0 * res.uncertainty_rot_deg


def test_real_robot_arm_data_no_false_alarms() -> None:
    """ETH ASL robot arm + SR300 (real, tests/data): the measured camera poses become virtual
    detections of a grid; the real data must pass the checks and agree with OpenCV's closed form."""
    from calibration.geometry import quaternion_to_matrix
    from calibration.handeye import opencv_handeye
    from tests.calibration.conftest import SR300_IR as sr300
    from tests.calibration.conftest import eth_arm_stations

    G, cam, dets, grid = eth_arm_stations()
    res = calibrate_handeye("eye-in-hand", G, dets, sr300, grid, RobotNoise(0.5, 0.1), sigma_px=0.3,
                            leave_one_out=False, estimate_robot_noise=True)
    codes = {p.code for p in res.problems}
    assert "pose_outlier" not in codes
    assert res.robot_noise.sigma_mm > 0.3  # a real arm's absolute error, not UR repeatability
    X_cv = opencv_handeye("eye-in-hand", G, [invert(make_transform(quaternion_to_matrix(r[4:8]), r[1:4]))
                                             for r in cam], "TSAI")
    rot_deg, trans_mm = transform_error_deg_mm(res.X, X_cv)
    assert trans_mm < 10.0 and rot_deg < 1.0
