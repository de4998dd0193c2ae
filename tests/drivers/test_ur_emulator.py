"""The UR emulator's dashboard server answers like a 5.11 controller (in-process, no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest

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


def _running_script(c: Controller, now: float) -> None:
    """The control script uploaded and started (the script server's part, without sockets)."""
    c.script.script_arrived(c.arm, now)
    c.step(now + 0.2)
    assert c.script.program_running


def _command(c: Controller, now: float, cmd: int, doubles: list[float], asynchronous: bool = False) -> None:
    """One ``ur_rtde`` command through the input registers: sent, done, cleared (each an input package)."""
    from drivers.peers.ur_emulator.rtde import apply_inputs

    regs = {f"input_double_register_{i}": v for i, v in enumerate(doubles)}
    apply_inputs(c, {"input_int_register_0": cmd, **regs, "input_int_register_1": int(asynchronous)})
    c.step(now)
    assert c.script.out_int[0] == 2, "the command was not done"
    apply_inputs(c, {"input_int_register_0": 0})
    c.step(now + 0.002)


def test_rtde_watchdog_stops_the_program_and_the_arm_when_the_inputs_stop() -> None:
    """setWatchdog (command 35, f from input double register 0) arms the script's watchdog on
    input_int_register_0: fed, the move goes on; silent for longer than 1/f, the program stops and the
    arm halts where it is. A stall of the emulator itself (one long tick) is not taken for silence."""
    from drivers.peers.ur_emulator.rtde import apply_inputs
    from drivers.peers.ur_emulator.script import CMD_MOVEL, CMD_SET_WATCHDOG

    c = Controller()
    t = 100.0
    _running_script(c, t)
    t += 0.2
    _command(c, t, CMD_SET_WATCHDOG, [10.0])  # 10 Hz: a gap over 0.1 s stops the program
    assert c.script.watchdog_hz == 10.0
    start = c.arm.T.copy()
    pose = T_to_pose(start)
    pose[0] += 0.25  # 250 mm at 0.05 m/s: 5 s
    t += 0.01
    _command(c, t, CMD_MOVEL, [*pose, 0.05, 1.2], asynchronous=True)
    for _ in range(50):  # 1 s of kicks every 20 ms (kickWatchdog's packages carry register 0)
        for _tick in range(10):
            t += 0.002
            c.step(t)
        apply_inputs(c, {"input_int_register_0": 0})
    assert c.script.program_running and c.arm.motion is not None
    c.step(t + 1.0)  # the emulator's own process stalled for 1 s: counted as one 10 ms tick, not silence
    t += 1.0
    assert c.script.program_running and c.script.watchdog_trips == 0
    for _tick in range(60):  # then 120 ms of silence at the controller's 500 Hz
        t += 0.002
        c.step(t)
    assert not c.script.program_running and c.script.watchdog_trips == 1
    assert "RTDE watchdog" in c.script.stop_reason
    assert c.arm.motion is None and c.script.watchdog_hz == 0.0  # the watchdog ends with the program
    frozen = c.arm.T.copy()
    moved_m = float(np.linalg.norm(frozen[:3, 3] - start[:3, 3]))
    assert 0.09 < moved_m < 0.12  # 2.1 s at 0.05 m/s (the arm moved through the stall): far from 250 mm
    for _tick in range(100):
        t += 0.002
        c.step(t)
    np.testing.assert_array_equal(c.arm.T, frozen)


def test_kick_watchdog_is_a_command_the_script_finishes_and_waits_to_have_cleared() -> None:
    """kickWatchdog's command 99 is not one of the script's realtime commands: done, then ready after a clear."""
    from drivers.peers.ur_emulator.rtde import apply_inputs
    from drivers.peers.ur_emulator.script import CMD_KICK_WATCHDOG

    c = Controller()
    _running_script(c, 0.0)
    apply_inputs(c, {"input_int_register_0": CMD_KICK_WATCHDOG})
    c.step(0.3)
    c.step(0.302)
    assert c.script.out_int[0] == 2
    apply_inputs(c, {"input_int_register_0": 0})
    c.step(0.304)
    assert c.script.out_int[0] == 1


def test_movel_follows_the_ur_controllers_trapezoid_and_turns_at_four_times_v() -> None:
    """``moveL`` as a UR controller times it (drivers.robot.ur_movel): position at ``v`` with ``a`` ramps, the
    tool's turn at 4 v rad/s (at most the UR5e's 180 deg/s joints) with 4 a ramps, the longer setting the time."""
    c = Controller()
    start = c.arm.T.copy()
    pose = T_to_pose(start)
    pose[0] += 0.3  # 300 mm at v = 1 m/s, a = 1.2 m/s^2: a triangle, 2 sqrt(0.3 / 1.2) = 1.0 s
    assert c.arm.start_linear(pose, speed_m_s=1.0, now=0.0, waiting=True, accel_m_s2=1.2)
    c.arm.step(0.25)  # a quarter of the time into the ramp: 1/8 of the way, not 1/4
    assert (c.arm.T[0, 3] - start[0, 3]) == pytest.approx(0.3 / 8, abs=1e-9)
    assert c.arm.tcp_speed(0.25)[0] == pytest.approx(0.3, abs=1e-6)  # 1.2 m/s^2 x 0.25 s
    assert c.arm.step(0.999) is None and c.arm.step(1.0) is not None
    turned = c.arm.T.copy()
    turned[:3, :3] = turned[:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg
    turn = T_to_pose(turned)
    assert c.arm.start_linear(turn, speed_m_s=0.25, now=10.0, waiting=True, accel_m_s2=1.2)
    # 4 v = 1 rad/s, 4 a = 4.8 rad/s^2: pi/2 / 1 + 1 / 4.8 s
    assert c.arm.motion is not None and c.arm.motion.duration_s == pytest.approx(math.pi / 2 + 1 / 4.8, abs=1e-6)
    assert c.arm.start_linear(turn, speed_m_s=1.0, now=20.0, waiting=True, accel_m_s2=20.0)
    # 4 v = 4 rad/s is held to the joints' pi rad/s: pi/2 / pi + pi / 80 s
    assert c.arm.motion is not None and c.arm.motion.duration_s == pytest.approx(0.5 + math.pi / 80, abs=1e-6)
