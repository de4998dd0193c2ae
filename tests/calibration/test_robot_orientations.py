"""The robot controllers' orientation conventions (calibration.geometry, the robot socket's pose formats)
against scipy's Rotation as an independent reference, on random rotations and on hand-checked poses
(docs/robot-socket.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration import geometry as g

ROTATIONS = Rotation.random(500, random_state=35)


def reference(R: np.ndarray, convention: str) -> np.ndarray:
    """What scipy says the convention's numbers are (computed without our code)."""
    r = Rotation.from_matrix(R)
    if convention == "ur":
        return r.as_rotvec()
    if convention == "abb":
        x, y, z, w = r.as_quat()
        q = np.array([w, x, y, z])
        return q if q[0] >= 0 else -q
    if convention == "kuka":  # A, B, C: intrinsic Z, Y', X''
        return r.as_euler("ZYX", degrees=True)
    return r.as_euler("xyz", degrees=True)  # fanuc W P R, yaskawa Rx Ry Rz: extrinsic X, Y, Z


@pytest.mark.parametrize("convention", g.ROBOT_ORIENTATIONS)
def test_each_convention_matches_scipy_on_random_rotations(convention: str) -> None:
    worst_value = worst_round_trip = 0.0
    for R in ROTATIONS.as_matrix():
        ours = np.array(g.matrix_to_robot_orientation(R, convention))
        worst_value = max(worst_value, float(np.max(np.abs(ours - reference(R, convention)))))
        back = g.robot_orientation_to_matrix(ours, convention)
        worst_round_trip = max(worst_round_trip, float(np.max(np.abs(back - R))))
    assert worst_value <= 1e-9, worst_value
    assert worst_round_trip <= 1e-9, worst_round_trip


@pytest.mark.parametrize("convention", ["fanuc", "kuka", "yaskawa"])
def test_our_angles_build_the_matrix_scipy_builds(convention: str) -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        a, b, c = rng.uniform(-179, 179), rng.uniform(-89, 89), rng.uniform(-179, 179)
        ours = g.robot_orientation_to_matrix([a, b, c], convention)
        seq = "ZYX" if convention == "kuka" else "xyz"
        assert np.max(np.abs(ours - Rotation.from_euler(seq, [a, b, c], degrees=True).as_matrix())) <= 1e-12


def test_gimbal_lock_still_round_trips() -> None:
    for b in (90.0, -90.0):
        R = g.zyx_deg_to_matrix(40.0, b, 25.0)
        for convention in ("fanuc", "kuka", "yaskawa"):
            back = g.robot_orientation_to_matrix(g.matrix_to_robot_orientation(R, convention), convention)
            assert np.max(np.abs(back - R)) <= 1e-9


def _same_angles(got: list[float], want: list[float]) -> bool:
    """Degrees equal modulo 360 (a robot takes 180 and -180 alike)."""
    return all(abs(math.remainder(x - y, 360.0)) < 1e-9 for x, y in zip(got, want, strict=True))


def test_the_hand_checked_pose_of_docs_robot_socket() -> None:
    # The tool pointing straight down (tool z = -base z), turned 90 degrees about base z:
    # R = Rz(90) @ Rx(180) = [[0, 1, 0], [1, 0, 0], [0, 0, -1]], worked out by hand in docs/robot-socket.md.
    R = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    s = math.sqrt(0.5)
    assert _same_angles(g.matrix_to_robot_orientation(R, "kuka"), [90.0, 0.0, 180.0])  # A B C
    assert _same_angles(g.matrix_to_robot_orientation(R, "fanuc"), [180.0, 0.0, 90.0])  # W P R
    assert _same_angles(g.matrix_to_robot_orientation(R, "yaskawa"), [180.0, 0.0, 90.0])  # Rx Ry Rz
    q = g.matrix_to_robot_orientation(R, "abb")  # q1..q4: 180 degrees about (1, 1, 0)/sqrt(2)
    assert np.allclose(np.abs(q), [0.0, s, s, 0.0], atol=1e-12) and q[1] * q[2] > 0
    rv = g.matrix_to_robot_orientation(R, "ur")
    assert np.allclose(np.abs(rv), [math.pi * s, math.pi * s, 0.0], atol=1e-9) and rv[0] * rv[1] > 0
    # The second hand-checked pose: Rz(90) @ Rx(90), a 120-degree turn about (1, 1, 1)/sqrt(3).
    R2 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert _same_angles(g.matrix_to_robot_orientation(R2, "kuka"), [90.0, 0.0, 90.0])
    assert _same_angles(g.matrix_to_robot_orientation(R2, "fanuc"), [90.0, 0.0, 90.0])
    assert np.allclose(g.matrix_to_robot_orientation(R2, "abb"), [0.5, 0.5, 0.5, 0.5], atol=1e-12)
    assert np.allclose(g.matrix_to_robot_orientation(R2, "ur"), [2 * math.pi / 3 / math.sqrt(3)] * 3, atol=1e-12)
    # And a turn about base z alone tells KUKA's order from FANUC's: A = 30 but R = 30.
    R3 = g.zyx_deg_to_matrix(30.0, 0.0, 0.0)
    assert _same_angles(g.matrix_to_robot_orientation(R3, "kuka"), [30.0, 0.0, 0.0])
    assert _same_angles(g.matrix_to_robot_orientation(R3, "fanuc"), [0.0, 0.0, 30.0])


def test_an_unknown_convention_and_a_zero_quaternion_are_refused() -> None:
    with pytest.raises(g.PoseError, match="unknown robot orientation convention 'staubli'"):
        g.matrix_to_robot_orientation(np.eye(3), "staubli")
    with pytest.raises(g.PoseError, match="non-zero norm"):
        g.robot_orientation_to_matrix([0, 0, 0, 0], "abb")
