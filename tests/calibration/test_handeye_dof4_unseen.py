"""4-DOF hand-eye says what its data cannot determine (the camera's height along the turning axis, the
tool's offset), what a wrong target height costs a mapping, and what to add: the stated cost is checked
against the mapping itself."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.handeye import RobotNoise, calibrate_handeye_dof4
from calibration.measure import pixel_to_robot
from calibration.synthetic import simulate_scara
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(7, 5, 25.0)
NOISE = RobotNoise(0.02, 0.01)


@pytest.mark.parametrize("setup", ["eye-in-hand", "eye-to-hand"])
def test_height_error_costs_what_the_result_says(setup: str) -> None:
    """A target height stated 2 mm wrong: mapped onto the true plane, a point r mm from the point under
    the camera moves r * 2 / d mm (d the working distance the result reports); onto the stated plane it does not."""
    s = simulate_scara(setup, 12, np.random.default_rng(3), camera=CAM, target=BOARD, robot_noise=NOISE)
    a = calibrate_handeye_dof4(setup, s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm, NOISE,
                               leave_one_out=False).to_json()
    b = calibrate_handeye_dof4(setup, s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm + 2.0, NOISE,
                               leave_one_out=False).to_json()
    info = a["fixed_by_constraint"]["not_determined_by_data"]
    assert ("tool z axis" if setup == "eye-in-hand" else "base z axis") in info["parameter"]
    assert "TCP" in info["tool_offset"] and any("6-DOF" in x for x in info["to_determine_it"])
    d_mm = info["working_distance_mm"]
    assert 300.0 < d_mm < 900.0
    k = info["map_error_mm_per_mm_of_height_at_100mm_from_nadir"]
    assert k == pytest.approx(100.0 / d_mm)
    assert info["from_target_z_sigma_mm_at_100mm_from_nadir"] == pytest.approx(k * 0.1)
    pose = s.G_recorded[0] if setup == "eye-in-hand" else None
    P = s.points_base_true[0]
    z_true = float(np.mean(P[:, 2]) * 1e3)
    X = np.array(a["T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"])
    nadir_mm = 1e3 * ((pose @ X) if pose is not None else X)[:2, 3]  # the point under the camera
    moved, stay = [], []
    for uv in ([200.0, 150.0], [1700.0, 1050.0], [958.0, 603.0]):
        pa = pixel_to_robot(a, uv, plane_z_mm=z_true, robot_pose=pose).xyz_mm
        pb = pixel_to_robot(b, uv, plane_z_mm=z_true, robot_pose=pose).xyz_mm
        r_mm = float(np.linalg.norm(pa[:2] - nadir_mm))
        moved.append((float(np.linalg.norm(pb[:2] - pa[:2])), r_mm * 2.0 / d_mm))
        pc = pixel_to_robot(b, uv, plane_z_mm=z_true + 2.0, robot_pose=pose).xyz_mm
        stay.append(float(np.linalg.norm(pc[:2] - pa[:2])))
    for got, said in moved:
        assert got == pytest.approx(said, rel=0.1, abs=0.02), moved
    assert max(m[0] for m in moved) > 0.3  # the corners really move
    assert max(stay) < 0.02, stay
