"""The ur_rtde adapter against the UR emulator, driven by the real ur_rtde clients on 127.0.0.1."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.base import DeviceOperationError, DeviceUnavailable, MotionLimits, MotionRejected, RobotStopped
from drivers.registry import adapter_class
from drivers.robot.ur_rtde import URRTDERobot
from drivers.peers.ur_emulator import HOME_Q, fixed_port_lock, forward_kinematics
from tests.drivers.peers import PeerProcess, wait_port

LIMITS = MotionLimits(
    x_mm=(-800, 800), y_mm=(-800, 800), z_mm=(0, 900), max_linear_speed_m_s=0.5, max_joint_speed_rad_s=1.0
)
SETTINGS = {
    "host": "127.0.0.1",
    "connect_timeout_s": 5.0,
    "state_max_age_s": 0.1,
    "stall_timeout_s": 0.5,
    "command_timeout_s": 5.0,
    "reconnect_initial_s": 0.2,
    "reconnect_max_s": 1.0,
}


@pytest.fixture
def robot(ur_emulator: PeerProcess) -> Iterator[URRTDERobot]:
    r = URRTDERobot("ur0", SETTINGS, LIMITS)
    r.connect()
    try:
        yield r
    finally:
        r.close()


def wait_for(predicate, timeout_s: float) -> float:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        try:
            if predicate():
                return time.monotonic() - t0
        except DeviceUnavailable:
            pass
        time.sleep(0.01)
    raise AssertionError(f"condition not met within {timeout_s} s")


def test_registry_and_settings_validation() -> None:
    cls = adapter_class("robot", "ur_rtde")
    assert cls is URRTDERobot
    with pytest.raises(ValueError, match="state_max_age_s"):
        cls.Settings.model_validate({"host": "127.0.0.1", "state_max_age_s": -1})
    with pytest.raises(ValueError, match="port"):
        cls.Settings.model_validate({"host": "127.0.0.1", "port": 30004})


@pytest.fixture(scope="class")
def class_robot() -> Iterator[URRTDERobot]:
    """One emulator and one connected adapter for the tests that do not break the peer."""
    with fixed_port_lock():
        peer = PeerProcess("drivers.peers.ur_emulator", ready_port=30003).start()
        r = URRTDERobot("ur0", SETTINGS, LIMITS)
        try:
            r.connect()
            yield r
        finally:
            r.close()
            peer.stop()


@pytest.fixture
def shared_robot(class_robot: URRTDERobot) -> URRTDERobot:
    """The class's adapter, put back in a known state before each test (so their order does not matter):
    connected, not latched, powered, brakes released, no protective stop, at the home joints."""
    r = class_robot
    r.connect()  # a no-op unless a test closed it
    r.resume()
    if r.state().metadata["safety_mode"] != "normal":
        r.unlock_protective_stop()
    if r.state().metadata["robot_mode"] != "running":
        r.power_on()
        r.brake_release()
    wait_for(lambda: r.state().metadata["robot_mode"] == "running" and r.state().metadata["safety_mode"] == "normal",
             5.0)
    r.move_joint(np.array(HOME_Q), speed_rad_s=1.0)
    return r


PROTECTIVE_STOP = """
import rtde_control
c = rtde_control.RTDEControlInterface("127.0.0.1")
c.triggerProtectiveStop()
c.disconnect()
"""


class TestAgainstOneEmulator:
    def test_state_is_fresh_and_matches_the_controller(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        st = robot.state()
        assert st.age_s() < 0.1
        np.testing.assert_allclose(st.T_base_tool, forward_kinematics(np.array(HOME_Q)), atol=1e-6)
        np.testing.assert_allclose(st.joints_rad, HOME_Q, atol=1e-9)
        assert st.mode == "running" and not st.moving
        # the stream is live: successive samples advance at the controller's rate
        t1 = robot.state().metadata["controller_time_s"]
        time.sleep(0.05)
        t2 = robot.state().metadata["controller_time_s"]
        assert 0.0 < t2 - t1 < 0.5  # the controller clock advances (loosely: the machine is shared)

    def test_move_linear_arrives_at_the_commanded_pose_and_speed(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        start = robot.state().T_base_tool
        target = start.copy()
        target[:3, 3] += [0.03, -0.02, 0.05]  # metres
        dist = float(np.linalg.norm([0.03, -0.02, 0.05]))
        robot.move_linear(start, speed_m_s=0.2)  # starts the control connection (not timed)
        t0 = time.monotonic()
        robot.move_linear(target, speed_m_s=0.2)
        elapsed = time.monotonic() - t0
        st = robot.state()
        assert np.linalg.norm(st.T_base_tool[:3, 3] - target[:3, 3]) < 0.2e-3
        np.testing.assert_allclose(st.T_base_tool[:3, :3], target[:3, :3], atol=1e-6)
        # moved at 0.2 m/s: dist / speed = 0.31 s (plus handshake), never the mm/s or instant
        assert dist / 0.2 * 0.9 < elapsed < dist / 0.2 + 1.0

    def test_move_joint_and_envelope(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        q = np.array(HOME_Q) + [0.1, 0.05, -0.05, 0.0, 0.0, 0.2]
        robot.move_joint(q, speed_rad_s=0.5)
        st = robot.state()
        np.testing.assert_allclose(st.joints_rad, q, atol=2e-3)
        np.testing.assert_allclose(st.T_base_tool, forward_kinematics(q), atol=1e-3)
        before = robot.state().T_base_tool
        outside = before.copy()
        outside[2, 3] = -0.2
        with pytest.raises(MotionRejected, match="z = -200.0 mm is outside"):
            robot.move_linear(outside, speed_m_s=0.1)
        with pytest.raises(MotionRejected, match="speed"):
            robot.move_linear(before, speed_m_s=2.0)
        # a joint target whose tool pose leaves the envelope is refused (the controller's kinematics)
        with pytest.raises(MotionRejected, match="outside"):
            robot.move_joint(np.array([0.0, -0.3, 2.2, 0.0, 0.0, 0.0]), speed_rad_s=0.5)
        time.sleep(0.05)
        np.testing.assert_allclose(robot.state().T_base_tool, before, atol=1e-9)

    def test_stop_interrupts_a_move(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        start = robot.state().T_base_tool
        target = start.copy()
        target[0, 3] += 0.2
        errors: list[Exception] = []

        def move() -> None:
            try:
                robot.move_linear(target, speed_m_s=0.1)
            except Exception as exc:
                errors.append(exc)

        th = threading.Thread(target=move)
        th.start()
        wait_for(lambda: robot.state().moving, 5.0)
        time.sleep(0.3)
        robot.stop()
        th.join(timeout=5)
        assert not th.is_alive()
        assert errors and isinstance(errors[0], RobotStopped)
        time.sleep(0.05)
        travelled = robot.state().T_base_tool[0, 3] - start[0, 3]
        assert 0.02 < travelled < 0.15

    def test_digital_io_and_dashboard(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        robot.set_digital_out(3, True)
        wait_for(lambda: robot.state().metadata["digital_out"][3], 2.0)
        assert robot.state().metadata["digital_in"][3]  # the emulator wires output i to input i
        robot.set_digital_out(3, False)
        wait_for(lambda: not robot.state().metadata["digital_in"][3], 2.0)
        assert robot.dashboard("robotmode") == "Robotmode: RUNNING"
        robot.dashboard("powerOff")
        wait_for(lambda: robot.state().metadata["robot_mode"] == "power_off", 2.0)
        target = robot.state().T_base_tool.copy()
        target[2, 3] += 0.01
        with pytest.raises(DeviceOperationError, match="power_off"):
            robot.move_linear(target, speed_m_s=0.1)
        robot.power_on()
        robot.brake_release()
        wait_for(lambda: robot.state().metadata["robot_mode"] == "running", 2.0)
        robot.move_linear(target, speed_m_s=0.1)
        assert abs(robot.state().T_base_tool[2, 3] - target[2, 3]) < 0.2e-3

    def test_protective_stop_is_reported_and_cleared_through_the_dashboard(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        target = robot.state().T_base_tool.copy()
        target[2, 3] += 0.01
        robot.move_linear(target, speed_m_s=0.1)
        # another ur_rtde client (the pendant's stand-in) triggers a protective stop through the protocol
        subprocess.run([sys.executable, "-c", PROTECTIVE_STOP], capture_output=True, timeout=60, check=True)
        wait_for(lambda: robot.state().metadata["safety_mode"] == "protective_stop", 2.0)
        assert robot.state().mode == "protective_stop"
        target[2, 3] += 0.01
        with pytest.raises(DeviceOperationError, match="protective_stop"):
            robot.move_linear(target, speed_m_s=0.1)
        assert "PROTECTIVE_STOP" in robot.dashboard("safetystatus")
        robot.unlock_protective_stop()
        wait_for(lambda: robot.state().metadata["safety_mode"] == "normal", 2.0)
        robot.move_linear(target, speed_m_s=0.1)  # the control script is uploaded again by itself
        assert abs(robot.state().T_base_tool[2, 3] - target[2, 3]) < 0.2e-3

    def test_close_and_connect_again(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        """The cell closes a failed device and connects it again later: the adapter must allow that."""
        robot.close()
        with pytest.raises(DeviceUnavailable, match="not connected"):
            robot.state()
        robot.connect()
        assert robot.state().age_s() < 0.1
        target = robot.state().T_base_tool.copy()
        target[0, 3] += 0.005
        robot.move_linear(target, speed_m_s=0.1)


def test_connect_fails_fast_without_a_controller(ur_ports: None) -> None:
    """A refused connection is reported at once, not after the connect timeout (the service must not hang)."""
    r = URRTDERobot("ur0", {**SETTINGS, "connect_timeout_s": 30.0}, LIMITS)
    t0 = time.monotonic()
    with pytest.raises(DeviceUnavailable, match="cannot connect RTDE to 127.0.0.1:30004"):
        r.connect()
    assert time.monotonic() - t0 < 10.0  # far below the 30 s connect timeout: the refusal ended the wait
    with pytest.raises(DeviceUnavailable, match="no RTDE state received yet"):
        r.state()
    h = r.health()
    assert h.available is False and "no RTDE state received yet" in h.reason
    r.close()
    r.close()  # idempotent


def test_peer_killed_mid_stream_and_restarted(robot: URRTDERobot, ur_emulator: PeerProcess) -> None:
    robot.state()
    ur_emulator.kill()
    # never a stale pose: unavailable within the max age (plus polling)
    t_unavailable = wait_for(lambda: not robot.health().available, 1.0)
    assert t_unavailable < 1.0
    with pytest.raises(DeviceUnavailable, match="reconnecting by itself"):
        robot.state()
    ur_emulator.start()
    # the adapter recovers by itself within 5 s (backoff capped at 1 s here) and counts the outage
    wait_for(lambda: robot.state().age_s() < 0.1 and robot.health().last_outage_s > 0, 5.0)
    h = robot.health()
    assert h.available and h.outages == 1 and h.reconnects >= 1 and h.last_outage_s > 0
    target = robot.state().T_base_tool.copy()
    target[1, 3] += 0.01
    robot.move_linear(target, speed_m_s=0.1)  # the control connection is rebuilt too


def test_frozen_peer_read_timeout(robot: URRTDERobot, ur_emulator: PeerProcess) -> None:
    ur_emulator.freeze()
    try:
        wait_for(lambda: not robot.health().available, 1.0)
        t0 = time.monotonic()
        with pytest.raises(DeviceUnavailable):
            robot.state()
        assert time.monotonic() - t0 < 0.5  # state() never blocks on the peer
    finally:
        ur_emulator.thaw()
    wait_for(lambda: robot.state().age_s() < 0.1, 6.0)
    assert robot.health().outages == 1


def test_malformed_replies(ur_ports: None) -> None:
    """A peer that answers the RTDE handshake with garbage: unavailable with a reason, no hang."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 30004))
    srv.listen(4)
    stop = threading.Event()

    def garbage() -> None:
        srv.settimeout(0.1)
        conns = []
        while not stop.is_set():
            try:
                c, _ = srv.accept()
            except TimeoutError:
                continue
            conns.append(c)
            c.sendall(b"\x00\x07Zgarbage!\xff\xff\x00" * 3)
        for c in conns:
            c.close()

    th = threading.Thread(target=garbage, daemon=True)
    th.start()
    wait_port(30004)
    r = URRTDERobot("ur0", {**SETTINGS, "connect_timeout_s": 1.5}, LIMITS)
    try:
        t0 = time.monotonic()
        with pytest.raises(DeviceUnavailable):
            r.connect()
        assert time.monotonic() - t0 < 3.0
        assert r.health().available is False
    finally:
        r.close()
        stop.set()
        th.join(timeout=2)
        srv.close()
