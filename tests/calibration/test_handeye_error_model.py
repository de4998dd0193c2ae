"""Hand-eye on robots whose error is not i.i.d.: the error model chosen by leave-one-out prediction
never predicts truly held-out stations worse than the fixed prior; joint intrinsics refinement.

The kinematic-error robot is the virtual cell's UR5e model with perturbed link lengths and joint
zero offsets (``drivers.sim.kinematics``): the recorded pose is the nominal one, the camera sees
the perturbed arm's — millimetres, pose-dependent.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, make_transform
from calibration.handeye import ERROR_MODELS, HandEyeResult, RobotNoise, calibrate_handeye, transform_error_deg_mm
from calibration.handeye.error_model import PARSIMONY, predicts_better
from calibration.measure import pixel_to_robot
from calibration.observations import Detection
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard
from drivers.sim.kinematics import KinematicError
from tests.calibration.conftest import SR300_IR, eth_arm_stations

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
TARGET = Chessboard(8, 6, 30.0)
STATED = RobotNoise(sigma_mm=0.05, sigma_deg=0.01)
N_CAL, N_HELD = 10, 4


def _kinematic_set(seed: int) -> tuple[list[np.ndarray], list[Detection]]:
    rng = np.random.default_rng(seed)
    Z = make_transform(np.diag([1.0, -1.0, -1.0]), [0.30, -0.05, -0.15])  # target within the UR5e's reach
    sim = simulate_handeye("eye-in-hand", N_CAL + N_HELD, rng, camera=CAM, target=TARGET,
                           robot_noise=RobotNoise(0.02, 0.005), Z_true=Z)
    arm = KinematicError(seed, link_sigma_mm=1.0, joint_offset_sigma_deg=0.05)
    tp = TARGET.points()
    dets = []
    for k, G in enumerate(sim.G_recorded):
        _, G_actual = arm.solve(G)
        C = invert(sim.X_true) @ invert(G_actual) @ sim.Z_true
        uv = CAM.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3]) + rng.normal(0.0, 0.05, (len(tp.ids), 2))
        dets.append(Detection(f"v{k:02d}.png", True, tp.ids.copy(), uv, image_size=CAM.size))
    return sim.G_recorded, dets


def _held_out_rms_px(res: HandEyeResult, G: list[np.ndarray], dets: list[Detection]) -> float:
    tp = TARGET.points()
    e = np.vstack([res.predict_pixels(g, tp.xyz_m) - d.uv for g, d in zip(G, dets, strict=True)])
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


@pytest.mark.parametrize("seed", [1, 2])
def test_chosen_error_model_never_predicts_held_out_stations_worse(seed: int) -> None:
    G, dets = _kinematic_set(seed)
    auto = calibrate_handeye("eye-in-hand", G[:N_CAL], dets[:N_CAL], CAM, TARGET, STATED)
    fixed = calibrate_handeye("eye-in-hand", G[:N_CAL], dets[:N_CAL], CAM, TARGET, STATED,
                              error_model="fixed_prior")
    cand = auto.error_model["candidates"]
    assert set(cand) == set(ERROR_MODELS)
    chosen = auto.error_model["chosen"]
    assert cand[chosen]["loo_prediction_rms_px"] <= cand["fixed_prior"]["loo_prediction_rms_px"]
    assert auto.to_json()["quality"]["loo_prediction_rms_px"] == pytest.approx(cand[chosen]["loo_prediction_rms_px"])
    # the stations neither run saw: the choice must not predict them worse than the fixed prior
    held_auto = _held_out_rms_px(auto, G[N_CAL:], dets[N_CAL:])
    held_fixed = _held_out_rms_px(fixed, G[N_CAL:], dets[N_CAL:])
    assert held_auto <= 1.05 * held_fixed + 0.02, (chosen, held_auto, held_fixed)
    # nor worse than a plain joint reprojection refinement (robot poses taken as exact)
    plain_loo = cand["plain_reprojection"]["loo_prediction_rms_px"]
    assert cand[chosen]["loo_prediction_rms_px"] <= (1 + PARSIMONY) * plain_loo
    plain = calibrate_handeye("eye-in-hand", G[:N_CAL], dets[:N_CAL], CAM, TARGET, STATED,
                              error_model="plain_reprojection", leave_one_out=False)
    held_plain = _held_out_rms_px(plain, G[N_CAL:], dets[N_CAL:])
    assert held_auto <= 1.05 * held_plain + 0.02, (chosen, held_auto, held_plain)


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_data_of_the_stated_model_keep_the_maximum_likelihood_fit(setup: str) -> None:
    """Held-out prediction barely tells the models apart on such data (each held-out station's own
    robot noise dominates it), so the default must not trade the ML fit for a chance winner."""
    for seed in (3, 8):
        sim = simulate_handeye(setup, 10, np.random.default_rng(seed), camera=CAM, target=TARGET,
                               robot_noise=STATED, pixel_sigma_px=0.05)
        auto = calibrate_handeye(setup, sim.G_recorded, sim.detections, CAM, TARGET, STATED)
        assert auto.error_model["chosen"] == "fixed_prior", auto.error_model
        assert list(auto.error_model["candidates"]) == ["fixed_prior"]
        assert "fits the residuals" in auto.error_model["rule"]
        assert abs(auto.error_model["stated_model_chi2_reduced"] - 1.0) < 0.1
        rot, trans = transform_error_deg_mm(auto.X, sim.X_true)
        assert rot < 3 * auto.uncertainty_rot_deg and trans < 3 * auto.uncertainty_trans_mm


def _loo(per_station_rms: list[float], points: int = 10) -> dict[str, object]:
    px = np.asarray(per_station_rms)
    return {"prediction_rms_px": float(np.sqrt(np.mean(px**2))),
            "per_pose": [{"rms_px": float(r), "points": points} for r in px]}


def test_another_model_must_predict_better_consistently_not_by_chance() -> None:
    ref = _loo([1.0, 1.2, 0.9, 1.1, 1.0, 0.8, 1.3, 1.0])
    consistent = _loo([0.8, 1.0, 0.7, 0.9, 0.8, 0.6, 1.1, 0.8])
    one_station = _loo([1.0, 1.2, 0.9, 1.1, 1.0, 0.8, 0.3, 1.0])  # all the gain from one held-out station
    tiny = _loo([0.995, 1.195, 0.895, 1.095, 0.995, 0.795, 1.295, 0.995])  # consistent but under 2 %
    assert predicts_better(consistent, ref)
    assert not predicts_better(one_station, ref)
    assert not predicts_better(tiny, ref)
    assert not predicts_better(ref, consistent)


def test_real_eth_arm_choice_never_worse_than_fixed_prior_on_held_out_stations() -> None:
    """ETH ASL robot arm + SR300 (real poses; virtual detections of a grid from the measured camera
    poses): calibrate on the first stations, predict the last ones."""
    G, _, dets, grid = eth_arm_stations()
    sr300, tp = SR300_IR, grid.points()
    n_cal = (2 * len(G)) // 3
    noise = RobotNoise(0.5, 0.1)
    auto = calibrate_handeye("eye-in-hand", G[:n_cal], dets[:n_cal], sr300, grid, noise, sigma_px=0.3)
    fixed = calibrate_handeye("eye-in-hand", G[:n_cal], dets[:n_cal], sr300, grid, noise, sigma_px=0.3,
                              error_model="fixed_prior")

    def held(res: HandEyeResult) -> float:
        e = np.vstack([res.predict_pixels(g, tp.xyz_m) - d.uv for g, d in zip(G[n_cal:], dets[n_cal:], strict=True)])
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))

    assert held(auto) <= 1.05 * held(fixed) + 0.05, auto.error_model


def test_joint_intrinsics_refinement_on_when_the_camera_verdict_is_uncertain() -> None:
    rng = np.random.default_rng(5)
    sim = simulate_handeye("eye-in-hand", 12, rng, camera=CAM, target=TARGET, robot_noise=STATED)
    off = CameraModel("opencv5", 1600, 1200, np.array([[1690.0, 0, 803], [0, 1691.0, 597], [0, 0, 1]]),
                      np.array([-0.07, 0.03, 0.0, 0.0, 0.0]))
    plain = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, off, TARGET, STATED,
                              error_model="fixed_prior")
    joint = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, off, TARGET, STATED,
                              error_model="fixed_prior", camera_verdict_ok=False)
    assert not plain.intrinsics_refined and joint.intrinsics_refined
    assert joint.camera is not None and abs(joint.camera.fx - 1700.0) < 0.3 * abs(off.fx - 1700.0)
    true_cam = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET, STATED,
                                 error_model="fixed_prior")
    # joint refinement predicts about as well as the true camera would, far better than the wrong one
    assert joint.loo["prediction_rms_px"] < 1.2 * true_cam.loo["prediction_rms_px"]
    assert joint.loo["prediction_rms_px"] < 0.7 * plain.loo["prediction_rms_px"]
    assert joint.to_json()["intrinsics_refined"] is True


def test_mapping_goes_through_the_systematic_correction_the_hand_eye_was_fitted_with() -> None:
    """A pixel of a target point, predicted at a station by the calibration, maps back onto that
    point (base frame) only if the map applies the same systematic robot correction as the fit."""
    G, dets = _kinematic_set(1)
    res = calibrate_handeye("eye-in-hand", G[:N_CAL], dets[:N_CAL], CAM, TARGET, STATED, error_model="systematic",
                            leave_one_out=False)
    he = res.to_json()
    A = np.asarray(he["error_model"]["systematic_A"])
    g = G[N_CAL]
    shift_mm = 1e3 * np.linalg.norm(A @ (g[:3, 3] - np.asarray(he["error_model"]["t_mean_m"])))
    assert shift_mm > 0.2  # the correction matters at this station
    P = TARGET.points().xyz_m[7]
    P_base = res.Z[:3, :3] @ P + res.Z[:3, 3]
    uv = res.predict_pixels(g, P[None])[0]
    m = pixel_to_robot(he, uv, camera=CAM, plane_z_mm=1e3 * P_base[2], robot_pose=g)
    assert np.linalg.norm(m.xyz_mm - 1e3 * P_base) < 0.01, (m.xyz_mm, 1e3 * P_base)
