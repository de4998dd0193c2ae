"""The UR emulator's dashboard server answers like a 5.11 controller (in-process, no sockets)."""

from __future__ import annotations

import numpy as np

from drivers.peers.ur_emulator import HOME_Q, dashboard_reply, forward_kinematics, inverse_kinematics
from drivers.peers.ur_emulator.arm import ROBOT_MODE_POWER_OFF, ROBOT_MODE_RUNNING, SAFETY_PROTECTIVE_STOP, T_to_pose
from drivers.peers.ur_emulator.controller import Controller


def test_dashboard_queries_actions_and_unknown_commands() -> None:
    c = Controller()
    assert dashboard_reply(c, "PolyscopeVersion") == ("URSoftware 5.11.1.108318 (Nov 29 2021)", False)
    assert dashboard_reply(c, "robotmode") == ("Robotmode: RUNNING", False)
    assert dashboard_reply(c, "running") == ("Program running: false", False)
    assert dashboard_reply(c, "power off") == ("Powering off", False)
    assert c.arm.robot_mode == ROBOT_MODE_POWER_OFF and dashboard_reply(c, "robotmode")[0] == "Robotmode: POWER_OFF"
    dashboard_reply(c, "power on")
    assert dashboard_reply(c, "robotmode")[0] == "Robotmode: IDLE"
    dashboard_reply(c, "brake release")
    assert c.arm.robot_mode == ROBOT_MODE_RUNNING
    assert dashboard_reply(c, "unlock protective stop")[0].startswith("Cannot unlock protective stop")
    c.arm.protective_stop()
    assert dashboard_reply(c, "safetystatus") == ("Safetystatus: PROTECTIVE_STOP", False)
    assert dashboard_reply(c, "unlock protective stop") == ("Protective stop releasing", False)
    assert c.arm.safety_mode != SAFETY_PROTECTIVE_STOP
    assert dashboard_reply(c, "setUserRole operator") == ("Setting user role: operator", False)
    assert dashboard_reply(c, "load /programs/a.urp") == ("File not found: /programs/a.urp", False)
    assert dashboard_reply(c, "quit") == ("Disconnected", True)
    assert dashboard_reply(c, "make coffee") == ("could not understand: 'make coffee'", False)


def test_arm_kinematics_round_trip_and_a_linear_move() -> None:
    q = np.array(HOME_Q) + [0.1, -0.05, 0.05, 0.0, 0.1, 0.2]
    T = forward_kinematics(q)
    q_back = inverse_kinematics(T, np.array(HOME_Q))
    assert q_back is not None
    np.testing.assert_allclose(forward_kinematics(q_back), T, atol=1e-9)
    far = T.copy()
    far[0, 3] += 5.0  # 5 m away: out of the UR5e's reach
    assert inverse_kinematics(far, q) is None
    c = Controller()
    start = c.arm.T.copy()
    pose = T_to_pose(start)
    pose[0] += 0.1  # 100 mm along x, same orientation: 1 s at 0.1 m/s
    target = start.copy()
    target[0, 3] += 0.1
    assert c.arm.start_linear(pose, speed_m_s=0.1, now=0.0, waiting=True)
    c.arm.step(0.5)  # halfway in time: halfway in space (a straight line at the commanded speed)
    np.testing.assert_allclose(c.arm.T[:3, 3], (start[:3, 3] + target[:3, 3]) / 2, atol=1e-9)
    finished = c.arm.step(1.5)  # past its 1 s duration
    assert finished is not None and c.arm.moves_completed == 1
    np.testing.assert_allclose(c.arm.T, target, atol=1e-9)
