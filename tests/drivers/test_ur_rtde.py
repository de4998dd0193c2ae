"""The ur_rtde adapter against the UR emulator, driven by the real ur_rtde clients on 127.0.0.1."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.base import (
    DeviceOperationError,
    DeviceUnavailable,
    DriverError,
    MotionLimits,
    MotionRejected,
    RobotStopped,
)
from drivers.peers.ur_emulator import HOME_Q, fixed_port_lock, forward_kinematics
from drivers.registry import adapter_class
from drivers.robot.ur_rtde import URRTDERobot
from tests.drivers.peers import PeerProcess, answers_within, fresh_state, wait_port

LIMITS = MotionLimits(
    x_mm=(-800, 800), y_mm=(-800, 800), z_mm=(0, 900), max_linear_speed_m_s=0.5, max_joint_speed_rad_s=1.0
)
SETTINGS = {
    "host": "127.0.0.1",
    "connect_timeout_s": 5.0,
    "reconnect_wait_s": 4.0,  # the default 2.5 s, widened: a fresh worker boots slowly on the loaded machine
    "state_max_age_s": 0.2,  # the default 0.1 s, widened for a loaded 2-core test machine
    "watchdog_min_frequency_hz": 4.0,  # the default 10 Hz, widened likewise (the kill tests below run 10 Hz)
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
        fresh_state(r)
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
    assert cls.Settings.model_validate({"host": "127.0.0.1"}).watchdog_min_frequency_hz == 10.0
    for hz in (0, 0.5, 200, "fast"):  # a watchdog cannot be switched off, nor asked for beyond 50 Hz
        with pytest.raises(ValueError, match="watchdog_min_frequency_hz"):
            cls.Settings.model_validate({"host": "127.0.0.1", "watchdog_min_frequency_hz": hz})


@pytest.fixture(scope="class")
def class_robot() -> Iterator[URRTDERobot]:
    """One emulator and one connected adapter for the tests that do not break the peer."""
    with fixed_port_lock():
        peer = PeerProcess("drivers.peers.ur_emulator", ready_port=30003).start()
        r = URRTDERobot("ur0", SETTINGS, LIMITS)
        try:
            r.connect()
            fresh_state(r)
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
    if fresh_state(r).metadata["safety_mode"] != "normal":
        r.unlock_protective_stop()
    if fresh_state(r).metadata["robot_mode"] != "running":
        r.power_on()
        r.brake_release()
    wait_for(lambda: r.state().metadata["robot_mode"] == "running" and r.state().metadata["safety_mode"] == "normal",
             5.0)
    r.move_joint(np.array(HOME_Q), speed_rad_s=1.0)
    fresh_state(r)
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
        assert st.age_s() < 0.2
        np.testing.assert_allclose(st.T_base_tool, forward_kinematics(np.array(HOME_Q)), atol=1e-6)
        np.testing.assert_allclose(st.joints_rad, HOME_Q, atol=1e-9)
        assert st.mode == "running" and not st.moving
        # the stream is live: successive samples advance at the controller's rate
        t1 = robot.state().metadata["controller_time_s"]
        wait_for(lambda: robot.state().metadata["controller_time_s"] > t1, 2.0)  # the controller clock advances

    def test_move_linear_arrives_at_the_commanded_pose_and_speed(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        start = robot.state().T_base_tool
        target = start.copy()
        target[:3, 3] += [0.03, -0.02, 0.05]  # metres
        dist = float(np.linalg.norm([0.03, -0.02, 0.05]))
        speeds: list[float] = []
        # moveL ramps its speed at the adapter's acceleration (the emulator plays a UR's trapezoid): 20 m/s^2 makes
        # the ramps 10 ms of the 0.3 s move, so the speed read is the cruise's
        config, robot.config = robot.config, robot.config.model_copy(update={"acceleration_m_s2": 20.0})
        try:
            mover = threading.Thread(target=lambda: robot.move_linear(target, speed_m_s=0.2))
            mover.start()
            # the controller reports the TCP speed it moves at: 0.2 m/s, never the mm/s reading or a jump
            wait_for(lambda: robot.state().moving, 5.0)
            while robot.state().moving:
                speeds.append(robot.state().metadata["tcp_speed_m_s"])
            mover.join(timeout=10)
        finally:
            robot.config = config
        st = robot.state()
        assert np.linalg.norm(st.T_base_tool[:3, 3] - target[:3, 3]) < 0.2e-3
        np.testing.assert_allclose(st.T_base_tool[:3, :3], target[:3, :3], atol=1e-6)
        assert speeds and float(np.median(speeds)) == pytest.approx(0.2, rel=0.02)
        assert dist > 0.05

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
        wait_for(lambda: robot.state().T_base_tool[0, 3] - start[0, 3] > 0.02, 5.0)
        robot.stop()
        th.join(timeout=5)
        assert not th.is_alive()
        assert errors and isinstance(errors[0], RobotStopped)
        wait_for(lambda: not robot.state().moving, 2.0)
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
        # another ur_rtde client (the pendant's stand-in) triggers a protective stop through the protocol.
        # A controller gives its RTDE input registers to one client at a time, and ours keeps the
        # watchdog of its control script fed through them: the adapter lets go of the controller first.
        robot.close()
        subprocess.run([sys.executable, "-c", PROTECTIVE_STOP], capture_output=True, timeout=60, check=True)
        robot.connect()
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

    def test_a_second_control_client_is_refused_while_the_adapter_holds_the_controller(
            self, shared_robot: URRTDERobot) -> None:
        """A controller gives an RTDE input register to one client: a second ur_rtde control interface
        (which would write our command and watchdog register) is refused, as on a real controller."""
        robot = shared_robot
        target = robot.state().T_base_tool.copy()
        target[2, 3] += 0.005
        robot.move_linear(target, speed_m_s=0.1)  # our control connection is up, its watchdog armed
        out = subprocess.run([sys.executable, "-c", PROTECTIVE_STOP], capture_output=True, text=True, timeout=60)
        assert out.returncode != 0 and "already in use" in out.stderr, out.stderr[-500:]
        assert robot.state().metadata["safety_mode"] == "normal"
        target[2, 3] -= 0.005
        robot.move_linear(target, speed_m_s=0.1)  # ours still works

    def test_close_and_connect_again(self, shared_robot: URRTDERobot) -> None:
        robot = shared_robot
        """The cell closes a failed device and connects it again later: the adapter must allow that."""
        robot.close()
        with pytest.raises(DeviceUnavailable, match="not connected"):
            robot.state()
        robot.connect()
        assert robot.state().age_s() < 0.2
        target = robot.state().T_base_tool.copy()
        target[0, 3] += 0.005
        robot.move_linear(target, speed_m_s=0.1)


def test_connect_fails_fast_without_a_controller(ur_ports: None) -> None:
    """A refused connection is reported at once, not after the connect timeout (the service must not hang)."""
    r = URRTDERobot("ur0", {**SETTINGS, "connect_timeout_s": 30.0}, LIMITS)
    err = answers_within(r.connect, 10.0)  # far below the 30 s connect timeout: the refusal ended the wait
    assert isinstance(err, DeviceUnavailable) and "cannot connect RTDE to 127.0.0.1:30004" in str(err)
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
    wait_for(lambda: not robot.health().available, 1.0)
    with pytest.raises(DeviceUnavailable, match="reconnecting by itself"):
        robot.state()
    ur_emulator.start()
    # the adapter recovers by itself within 5 s (backoff capped at 1 s here) and counts the outage
    wait_for(lambda: robot.state().age_s() < 0.2 and (robot.health().last_outage_s or 0) > 0, 5.0)
    h = robot.health()
    assert h.available and h.outages == 1 and h.reconnects >= 1 and (h.last_outage_s or 0) > 0
    target = robot.state().T_base_tool.copy()
    target[1, 3] += 0.01
    robot.move_linear(target, speed_m_s=0.1)  # the control connection is rebuilt too


def test_frozen_peer_read_timeout(robot: URRTDERobot, ur_emulator: PeerProcess) -> None:
    ur_emulator.freeze()
    try:
        wait_for(lambda: not robot.health().available, 1.0)
        assert isinstance(answers_within(robot.state, 0.5), DeviceUnavailable)  # never blocks on the peer
        # the cell closes the lost robot and opens it again: a frozen (or unreachable) controller
        # refuses no connection, yet connect() answers within the reconnect wait, not connect_timeout_s
        robot.close()
        err = answers_within(robot.connect, 6.0)  # reconnect_wait_s (4 s here) plus margin, not connect_timeout_s
        assert isinstance(err, DeviceUnavailable) and "within 4 s" in str(err), repr(err)
    finally:
        ur_emulator.thaw()
    wait_for(lambda: robot.state().age_s() < 0.2, 6.0)
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
        assert isinstance(answers_within(r.connect, 3.0), DeviceUnavailable)
        assert r.health().available is False
    finally:
        r.close()
        stop.set()
        th.join(timeout=2)
        srv.close()


# -- faults: the service's own deadlines hold while the controller is gone ---------------------------

SERVICE_DEADLINE_S = 3.0
"""The service's device-call deadline (cellctl.api.deps.DEVICE_CALL_TIMEOUT_S): no request may wait longer."""


def test_requests_fail_fast_during_an_outage(robot: URRTDERobot, ur_emulator: PeerProcess) -> None:
    target = robot.state().T_base_tool.copy()
    target[2, 3] += 0.01
    robot.move_linear(target, speed_m_s=0.1)  # the control worker is up and connected
    ur_emulator.kill()
    wait_for(lambda: not robot.health().available, 2.0)
    calls: dict[str, Callable[[], object]] = {
        "move": lambda: robot.move_linear(target, speed_m_s=0.1),
        "dashboard": lambda: robot.dashboard("robotmode"),
        "digital_out": lambda: robot.set_digital_out(1, True),
        "state": robot.state,
    }
    for name, call in calls.items():
        err = answers_within(call, SERVICE_DEADLINE_S)
        assert isinstance(err, DeviceUnavailable), f"{name}: {err!r}"
    err = answers_within(lambda: robot.stop(by="test"), SERVICE_DEADLINE_S)  # tried, typed, latched
    assert err is None or isinstance(err, DriverError), repr(err)
    assert robot.motion.latched
    # the cell closes a failed device and opens it again after its back-off: that connect fails fast too
    robot.close()
    err = answers_within(robot.connect, SERVICE_DEADLINE_S)
    assert isinstance(err, DeviceUnavailable), repr(err)


OWNER = """
import sys, time
from drivers.base import MotionLimits
from drivers.robot.ur_rtde import URRTDERobot
r = URRTDERobot("ur0", {"host": "127.0.0.1", "connect_timeout_s": 20.0},
                MotionLimits(x_mm=(-800, 800), y_mm=(-800, 800), z_mm=(0, 900), max_linear_speed_m_s=0.5))
r.connect()
r.dashboard("robotmode")  # the control worker too
print("ready", flush=True)
time.sleep(600)
"""


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                out.append(int(stat.parent.name))
    return out


def _gone(pid: int) -> bool:
    """True when ``pid`` has exited (a zombie waiting for its new parent to reap it counts as exited)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_kill_9_of_the_owner_takes_its_workers_with_it(ur_emulator: PeerProcess) -> None:
    """The service is killed with SIGKILL: its UR worker processes must not stay alive and connected."""
    owner = subprocess.Popen([sys.executable, "-c", OWNER], cwd=Path(__file__).resolve().parents[2],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        assert owner.stdout is not None
        assert owner.stdout.readline().strip() == b"ready"
        workers = _children(owner.pid)
        names = [Path(f"/proc/{p}/cmdline").read_bytes() for p in workers]
        assert len(workers) >= 2, names  # the state and the control worker (and multiprocessing's tracker)
        owner.kill()
        owner.wait(timeout=10)
        wait_for(lambda: all(_gone(p) for p in workers), 10.0)
    finally:
        if owner.poll() is None:
            owner.kill()
            owner.wait(timeout=10)
        for p in _children(owner.pid):
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)


MOVING_OWNER = """
import sys
import numpy as np
from drivers.base import MotionLimits
from drivers.robot.ur_rtde import URRTDERobot
r = URRTDERobot("ur0", {"host": "127.0.0.1", "connect_timeout_s": 20.0, "state_max_age_s": 0.3},
                MotionLimits(x_mm=(-800, 800), y_mm=(-800, 800), z_mm=(0, 900), max_linear_speed_m_s=0.5))
r.connect()
target = r.state().T_base_tool.copy()
target[0, 3] += 0.25
print("moving", flush=True)
r.move_linear(target, 0.05)  # 5 s; the test kills this process on the way
"""


def test_kill_9_of_the_owner_mid_move_the_rtde_watchdog_halts_the_arm(ur_emulator: PeerProcess) -> None:
    """The process that drives the arm dies mid-move: its control worker dies with it, the watchdog's
    kicks stop, and the controller stops the program and the arm within the watchdog period (10 Hz)."""
    import rtde_receive

    receiver = rtde_receive.RTDEReceiveInterface("127.0.0.1")
    owner = subprocess.Popen([sys.executable, "-c", MOVING_OWNER], cwd=Path(__file__).resolve().parents[2],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        x0 = receiver.getActualTCPPose()[0]
        wait_for(lambda: receiver.getActualTCPPose()[0] - x0 > 0.03, 30.0)  # 0.6 s into the move
        x_kill = receiver.getActualTCPPose()[0]
        owner.kill()
        t_kill = time.monotonic()
        owner.wait(timeout=10)
        wait_for(lambda: receiver.getRuntimeState() != 2, 2.0)  # the control script was stopped
        halted_s = time.monotonic() - t_kill
        x_halt = receiver.getActualTCPPose()[0]
        assert halted_s < 0.1 + 0.5  # the watchdog period, plus a margin for a loaded machine
        assert x_halt - x_kill < 0.05 * (0.1 + 0.5)
        time.sleep(0.3)
        assert receiver.getActualTCPPose()[0] == x_halt  # frozen
        assert x0 + 0.25 - x_halt > 0.15  # far from the target
    finally:
        receiver.disconnect()
        if owner.poll() is None:
            owner.kill()
            owner.wait(timeout=10)
