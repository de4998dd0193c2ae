"""The camera's own uncertainty in the hand-eye covariance: with intrinsics off by a draw from their
covariance, the hand-eye error matches the reported 1-σ only when that covariance is passed in."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.handeye import HandEyeError, RobotNoise, calibrate_handeye, transform_error_deg_mm
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
TARGET = Chessboard(8, 6, 30.0)
NOISE = RobotNoise(0.02, 0.005)
SD = np.array([3.0, 3.0, 2.5, 2.5, 0.004, 0.01, 1e-4, 1e-4, 1e-6])
"""1-σ of fx, fy, cx, cy (px) and k1, k2, p1, p2, k3: a camera calibrated from few views."""


def _cov() -> np.ndarray:
    cov = np.diag(SD**2)
    cov[0, 1] = cov[1, 0] = 0.9 * SD[0] * SD[1]  # fx and fy move together, as they do in a calibration
    return cov


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_truth_within_the_uncertainty_only_with_the_camera_covariance(setup: str) -> None:
    cov = _cov()
    L = np.linalg.cholesky(cov)
    without, with_cov = [], []
    for seed in range(6):
        rng = np.random.default_rng(40 + seed)
        sim = simulate_handeye(setup, 10, rng, camera=CAM, target=TARGET, robot_noise=NOISE, pixel_sigma_px=0.05)
        c = np.concatenate([[1700.0, 1700.0, 800.0, 600.0], CAM.dist]) + L @ rng.normal(size=9)
        off = CameraModel("opencv5", 1600, 1200, np.array([[c[0], 0, c[2]], [0, c[1], c[3]], [0, 0, 1]]), c[4:])
        r0 = calibrate_handeye(setup, sim.G_recorded, sim.detections, off, TARGET, NOISE, leave_one_out=False)
        r1 = calibrate_handeye(setup, sim.G_recorded, sim.detections, off, TARGET, NOISE, leave_one_out=False,
                               camera_covariance=cov)
        assert r1.camera_uncertainty == "propagated" and r0.camera_uncertainty == "none"
        assert np.allclose(r1.X, r0.X)  # propagation changes the covariance, not the estimate
        rot, trans = transform_error_deg_mm(r1.X, sim.X_true)
        without.append((rot / r0.uncertainty_rot_deg, trans / r0.uncertainty_trans_mm))
        with_cov.append((rot / r1.uncertainty_rot_deg, trans / r1.uncertainty_trans_mm))
    q0 = np.sqrt(np.mean(np.square(without), axis=0))
    q1 = np.sqrt(np.mean(np.square(with_cov), axis=0))
    assert np.all(q0 > 3.0), q0  # the camera's error dominates: ignoring it is overconfident
    assert np.all((q1 > 0.5) & (q1 < 2.0)), q1


def test_camera_covariance_as_prior_when_intrinsics_are_refined() -> None:
    sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(3), camera=CAM, target=TARGET,
                           robot_noise=NOISE, pixel_sigma_px=0.05)
    res = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET, NOISE, leave_one_out=False,
                            refine_intrinsics=True, camera_covariance=_cov())
    assert res.intrinsics_refined and res.camera_uncertainty == "prior"
    assert res.to_json()["uncertainty"]["camera"] == "prior"


def test_camera_covariance_of_the_wrong_size_is_named() -> None:
    sim = simulate_handeye("eye-in-hand", 6, np.random.default_rng(4), camera=CAM, target=TARGET,
                           robot_noise=NOISE, pixel_sigma_px=0.05)
    with pytest.raises(HandEyeError, match="camera covariance must be 9x9"):
        calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, TARGET, NOISE, leave_one_out=False,
                          camera_covariance=np.eye(5))
