"""Pixel → robot point with uncertainty, for hand-eye (both setups) and n-point calibrations."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, transform_points, transform_to_ur_pose
from calibration.handeye import RobotNoise, calibrate_handeye
from calibration.measure import MappingError, pixel_to_robot
from calibration.npoint import fit_npoint
from calibration.synthetic import simulate_handeye, simulate_npoint
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
TARGET = Chessboard(8, 6, 30.0)
NOISE = RobotNoise(0.05, 0.01)


@pytest.fixture(scope="module", params=["eye-in-hand", "eye-to-hand"])
def calibrated(request: pytest.FixtureRequest):
    setup = request.param
    sim = simulate_handeye(setup, 10, np.random.default_rng(21), camera=CAM, target=TARGET, robot_noise=NOISE)
    res = calibrate_handeye(setup, sim.G_recorded, sim.detections, CAM, TARGET, NOISE, leave_one_out=False)
    # the JSON round trip is what the CLI and the service use
    return sim, json.loads(json.dumps(res.to_json()))


def test_handeye_point_within_uncertainty(calibrated) -> None:
    sim, he = calibrated
    k = 2
    if sim.setup == "eye-in-hand":
        T_base_cam = sim.G_true[k] @ sim.X_true
        pose = transform_to_ur_pose(sim.G_true[k])
    else:
        T_base_cam = sim.X_true
        pose = None
    # a point on a working plane 30 mm below where the camera's axis meets the target region
    hit = T_base_cam[:3, 3] + 0.45 * T_base_cam[:3, 2]
    P = hit - np.array([0.0, 0.0, 0.03])
    uv = CAM.project(transform_points(invert(T_base_cam), P[None]))[0]
    out = pixel_to_robot(he, uv, plane_z_mm=P[2] * 1e3, robot_pose=pose, pixel_sigma_px=0.0)
    err = out.xyz_mm - P * 1e3
    total = float(np.sqrt(np.trace(out.cov_mm2)))
    assert abs(err[2]) < 1e-6
    assert np.linalg.norm(err) < 3.0 * total
    assert 0.0 < total < 1.0
    js = out.to_json()
    assert {"x_mm", "y_mm", "z_mm", "sigma"} <= set(js)
    # pixel noise adds to the uncertainty
    noisy = pixel_to_robot(he, uv, plane_z_mm=P[2] * 1e3, robot_pose=pose, pixel_sigma_px=0.5)
    assert np.trace(noisy.cov_mm2) > np.trace(out.cov_mm2)


def test_handeye_needs_plane_and_pose(calibrated) -> None:
    sim, he = calibrated
    with pytest.raises(MappingError, match="working plane's height") as err:
        pixel_to_robot(he, [800, 600])
    assert (err.value.inputs, err.value.need) == (("plane_z_mm",), "give") and "--" not in str(err.value)
    if sim.setup == "eye-in-hand":
        with pytest.raises(MappingError, match="robot pose at capture"):
            pixel_to_robot(he, [800, 600], plane_z_mm=0.0)
    else:
        with pytest.raises(MappingError, match="not used"):
            pixel_to_robot(he, [800, 600], plane_z_mm=0.0, robot_pose=[0.4, 0, 0.3, 0, 3.14, 0])


def test_npoint_point_within_uncertainty() -> None:
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 960], [0, 1900.0, 600], [0, 0, 1]]), np.zeros(5))
    uv, xy, truth = simulate_npoint(np.random.default_rng(4), cam, tilt_deg=1.5)
    js = fit_npoint(uv, xy).to_json()
    q = np.array([[900.0, 650.0]])
    out = pixel_to_robot(js, q[0], plane_z_mm=12.0)
    err = out.xyz_mm[:2] - truth(q)[0]
    assert out.xyz_mm[2] == 12.0
    assert np.linalg.norm(err) < 3.0 * np.sqrt(np.trace(out.cov_mm2))
    with pytest.raises(MappingError, match="not used"):
        pixel_to_robot(js, q[0], robot_pose=[0, 0, 0, 0, 0, 0])


def test_unknown_calibration_refused() -> None:
    with pytest.raises(MappingError, match="np.json"):
        pixel_to_robot({"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, [1, 2])
