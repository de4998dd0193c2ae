"""The Modbus TCP robot and IO adapters against the pymodbus robot simulator on 127.0.0.1."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.base import DeviceOperationError, DeviceTimeout, DeviceUnavailable, MotionLimits, RobotStopped
from drivers.io.modbus import ModbusDigitalIO
from drivers.registry import adapter_class
from drivers.robot.modbus import ModbusRobot
from tests.drivers.peers import GarbageServer, PeerProcess, answers_within, free_port

LIMITS = MotionLimits(x_mm=(-900, 900), y_mm=(-900, 900), z_mm=(0, 900), max_linear_speed_m_s=1.0)


def _settings(port: int, **kw: object) -> dict[str, object]:
    return {
        "host": "127.0.0.1",
        "port": port,
        "timeout_s": 0.3,
        "state_max_age_s": 0.3,
        "poll_hz": 50,
        "reconnect_initial_s": 0.1,
        "reconnect_max_s": 0.5,
        **kw,
    }


def start_sim(port: int, *args: str) -> PeerProcess:
    return PeerProcess("drivers.peers.modbus_robot", "--port", str(port), *args, ready_port=port).start()


@pytest.fixture
def sim() -> Iterator[PeerProcess]:
    peer = start_sim(free_port())
    try:
        yield peer
    finally:
        peer.stop()


@pytest.fixture
def robot(sim: PeerProcess) -> Iterator[ModbusRobot]:
    port = int(sim.args[1])
    r = ModbusRobot("plc0", _settings(port), LIMITS)
    r.connect()
    try:
        yield r
    finally:
        r.close()


def wait_for(predicate: Callable[[], bool], timeout_s: float) -> float:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        try:
            if predicate():
                return time.monotonic() - t0
        except (DeviceUnavailable, DeviceOperationError):
            pass
        time.sleep(0.01)
    raise AssertionError(f"condition not met within {timeout_s} s")


def test_registry_and_settings() -> None:
    assert adapter_class("robot", "modbus") is ModbusRobot
    assert adapter_class("io", "modbus") is ModbusDigitalIO
    with pytest.raises(ValueError, match="data_type"):
        ModbusRobot.Settings.model_validate({"host": "h", "speed": {"address": 1, "data_type": "float64"}})
    with pytest.raises(ValueError, match="heartbeat_timeout_s"):
        ModbusRobot.Settings.model_validate({"host": "h", "poll_hz": 1, "heartbeat_timeout_s": 0.5})


def _target(robot: ModbusRobot, dx_m: float, dy_m: float, dz_m: float, yaw_deg: float = 0.0) -> np.ndarray:
    T = robot.state().T_base_tool.copy()
    T[:3, 3] += [dx_m, dy_m, dz_m]
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ T[:3, :3]
    return T


@pytest.fixture(scope="class")
def class_peer() -> Iterator[tuple[ModbusRobot, PeerProcess]]:
    """One simulator and one connected adapter for the tests that do not break the peer."""
    port = free_port()
    peer = start_sim(port)
    r = ModbusRobot("plc0", _settings(port), LIMITS)
    try:
        r.connect()
        yield r, peer
    finally:
        r.close()
        peer.stop()


HOME = np.eye(4)
HOME[:3, :3] = Rotation.from_euler("xyz", [180, 0, 0], degrees=True).as_matrix()
HOME[:3, 3] = [0.4, 0.0, 0.3]  # the simulator's start pose (400, 0, 300 mm)


@pytest.fixture
def shared(class_peer: tuple[ModbusRobot, PeerProcess]) -> tuple[ModbusRobot, PeerProcess]:
    """The class's adapter put back before each test (not latched, outputs off, at the start pose),
    so the tests do not depend on their order."""
    robot, _ = class_peer
    robot.resume()
    for ch in range(8):
        robot.set_digital_out(ch, False)
    if np.linalg.norm(robot.state().T_base_tool[:3, 3] - HOME[:3, 3]) > 1e-6 or not np.allclose(
            robot.state().T_base_tool[:3, :3], HOME[:3, :3], atol=1e-6):
        robot.move_linear(HOME, speed_m_s=0.5)
    return class_peer


class TestAgainstOneSimulator:
    def test_state_decodes_the_register_map(self, shared: tuple[ModbusRobot, PeerProcess]) -> None:
        robot, _ = shared
        st = robot.state()
        np.testing.assert_allclose(st.T_base_tool[:3, 3], [0.4, 0.0, 0.3], atol=1e-6)  # 400, 0, 300 mm
        np.testing.assert_allclose(
            st.T_base_tool[:3, :3], Rotation.from_euler("xyz", [180, 0, 0], degrees=True).as_matrix(), atol=1e-6
        )
        assert st.age_s() < 0.3 and st.metadata["status"] == "ready" and not st.moving

    def test_move_linear_handshake_units_and_watchdog(self, shared: tuple[ModbusRobot, PeerProcess]) -> None:
        robot, _ = shared
        # 0.25 m at 0.2 m/s = 1.25 s: longer than the PLC's 1 s watchdog, so our heartbeat must run
        target = _target(robot, 0.15, -0.2, 0.0, yaw_deg=30)
        start = robot.state().T_base_tool
        samples: list[tuple[float, float]] = []  # (sample host time s, distance from start m) while moving
        mover = threading.Thread(target=lambda: robot.move_linear(target, speed_m_s=0.2))
        mover.start()
        while mover.is_alive():
            with contextlib.suppress(DeviceUnavailable):
                s = robot.state()
                if s.moving:
                    samples.append((s.timestamp_s, float(np.linalg.norm(s.T_base_tool[:3, 3] - start[:3, 3]))))
            time.sleep(0.01)
        # moved at 0.2 m/s (the m/s -> mm/s register unit), by the controller's own samples
        t, d = np.array(samples).T
        assert len(samples) > 10 and np.polyfit(t - t[0], d, 1)[0] == pytest.approx(0.2, rel=0.1)
        st = robot.state()
        np.testing.assert_allclose(st.T_base_tool, target, atol=1e-5)
        assert st.metadata["status"] == "ready"  # the command was cleared
        with pytest.raises(DeviceOperationError, match="target out of reach"):
            robot.move_linear(_target(robot, 0.3, 0.45, 0.5), speed_m_s=0.2)  # inside our box, beyond its reach
        robot.move_linear(_target(robot, 0.0, 0.0, 0.02), speed_m_s=0.5)  # recovers from the refused move

    def test_stop_and_digital_io(self, shared: tuple[ModbusRobot, PeerProcess]) -> None:
        robot, sim = shared
        start = robot.state().T_base_tool
        errors: list[Exception] = []

        def move() -> None:
            try:
                robot.move_linear(_target(robot, 0.0, 0.3, 0.0), speed_m_s=0.1)
            except Exception as exc:
                errors.append(exc)

        th = threading.Thread(target=move)
        th.start()
        wait_for(lambda: robot.state().moving, 2.0)
        # Stop once it has gone 25 mm (about 0.25 s at 0.1 m/s), wherever the loaded machine's clock is.
        wait_for(lambda: robot.state().T_base_tool[1, 3] - start[1, 3] > 0.025, 10.0)
        robot.stop()
        th.join(timeout=5)
        assert errors and isinstance(errors[0], RobotStopped)
        assert robot.resume()
        travelled = robot.state().T_base_tool[1, 3] - start[1, 3]
        assert 0.02 < travelled < 0.1

        robot.set_digital_out(5, True)
        wait_for(lambda: robot.state().metadata["digital_in"][5], 1.0)
        io = ModbusDigitalIO("io0", {"host": "127.0.0.1", "port": int(sim.args[1]), "timeout_s": 0.3})
        with io:
            assert io.read_input(5) and io.read_output(5)
            io.write_output(5, False)
            assert not io.read_input(5)
            with pytest.raises(DeviceOperationError, match="output 9 is not in 0..7"):
                io.write_output(9, True)

    def test_close_and_connect_again(self, shared: tuple[ModbusRobot, PeerProcess]) -> None:
        """The cell closes a failed device and connects it again later: the adapter must allow that."""
        robot, _ = shared
        robot.close()
        with pytest.raises(DeviceUnavailable, match="no state yet"):
            robot.state()
        robot.connect()
        assert robot.state().age_s() < 0.3


def test_little_word_order() -> None:
    port = free_port()
    peer = start_sim(port, "--word-order", "little")
    r = ModbusRobot("plc0", _settings(port, word_order="little"), LIMITS)
    try:
        r.connect()
        np.testing.assert_allclose(r.state().T_base_tool[:3, 3], [0.4, 0.0, 0.3], atol=1e-6)
        target = _target(r, -0.05, 0.05, 0.05)
        r.move_linear(target, speed_m_s=0.5)
        np.testing.assert_allclose(r.state().T_base_tool, target, atol=1e-5)
    finally:
        r.close()
        peer.stop()


def test_connect_timeout() -> None:
    port = free_port()  # nothing listens
    r = ModbusRobot("plc0", _settings(port), LIMITS)
    err = answers_within(r.connect, 2.0)
    assert isinstance(err, DeviceUnavailable) and "no answer from Modbus TCP" in str(err)
    assert r.health().available is False
    r.close()
    r.close()
    with pytest.raises(DeviceUnavailable, match="cannot connect"):
        ModbusDigitalIO("io0", {"host": "127.0.0.1", "port": port}).open()


def test_peer_killed_and_restarted(robot: ModbusRobot, sim: PeerProcess) -> None:
    sim.kill()
    wait_for(lambda: not robot.health().available, 1.0)
    with pytest.raises(DeviceUnavailable, match="reconnecting"):
        robot.state()
    sim.start()
    wait_for(lambda: robot.state().age_s() < 0.3, 5.0)  # stated: within 5 s (backoff <= 0.5 s)
    h = robot.health()
    assert h.outages == 1 and h.reconnects >= 1 and (h.last_outage_s or 0) > 0
    robot.move_linear(_target(robot, 0.0, 0.0, 0.01), speed_m_s=0.5)


def test_frozen_peer_read_timeout(robot: ModbusRobot, sim: PeerProcess) -> None:
    sim.freeze()
    try:
        wait_for(lambda: not robot.health().available, 1.5)
        assert isinstance(answers_within(robot.state, 2.0), DeviceUnavailable)
        up = HOME.copy()
        up[2, 3] += 0.01  # a valid target: the move itself must refuse at once, not wait on the frozen peer
        err = answers_within(lambda: robot.move_linear(up, speed_m_s=0.5), 2.0)
        assert isinstance(err, (DeviceTimeout, DeviceUnavailable)), repr(err)
    finally:
        sim.thaw()
    wait_for(lambda: robot.state().age_s() < 0.3, 5.0)
    assert robot.health().outages == 1


def test_malformed_replies() -> None:
    peer = GarbageServer().start()
    r = ModbusRobot("plc0", _settings(peer.port), LIMITS)
    try:
        assert isinstance(answers_within(r.connect, 2.0), DeviceUnavailable)
        assert "Modbus" in r.health().reason
    finally:
        r.close()
        peer.stop()


def test_register_codec_types_word_order_and_scale() -> None:
    """int16/uint16/int32/uint32/float32 with scale, both word orders: what a PLC map may use."""
    from drivers.robot.modbus_map import RegisterSpec

    for order in ("big", "little"):
        r = ModbusRobot("plc0", {"host": "127.0.0.1", "word_order": order}, LIMITS)
        cases = [("int16", 0.1, -123.4, 1), ("uint16", 1.0, 65000.0, 1), ("int32", 0.001, -654321.123, 2),
                 ("uint32", 1.0, 4_000_000_000.0, 2), ("float32", 1.0, 1234.5, 2)]
        for dtype, scale, value, width in cases:
            spec = RegisterSpec(address=0, data_type=dtype, scale=scale)  # type: ignore[arg-type]
            regs = r._encode(spec, value)
            assert len(regs) == width and all(0 <= v <= 0xFFFF for v in regs)
            assert r._decode(spec, regs) == pytest.approx(value, abs=scale / 2)
        # the word order really changes the layout of 32-bit values
        spec = RegisterSpec(address=0, data_type="int32", scale=1.0)
        regs = r._encode(spec, 0x00010002)
        assert regs == ([1, 2] if order == "big" else [2, 1])


MOVING_OWNER = """
import sys
from drivers.base import MotionLimits
from drivers.robot.modbus import ModbusRobot
r = ModbusRobot("plc0", {"host": "127.0.0.1", "port": int(sys.argv[1]), "timeout_s": 0.3, "state_max_age_s": 0.3},
                MotionLimits(x_mm=(-900, 900), y_mm=(-900, 900), z_mm=(0, 900), max_linear_speed_m_s=1.0))
r.connect()
target = r.state().T_base_tool.copy()
target[1, 3] += 0.25
print("moving", flush=True)
r.move_linear(target, 0.1)  # 2.5 s; the test kills this process on the way
"""


def test_kill_9_of_the_owner_mid_move_the_plc_watchdog_halts_the_robot(sim: PeerProcess) -> None:
    """The process that drives the robot dies mid-move: our heartbeat (register 50) stops changing and
    the simulated PLC stops the move within its watchdog (1 s), reporting error 2 (watchdog expired)."""
    import subprocess
    import sys
    from pathlib import Path

    port = int(sim.args[1])
    watcher = ModbusRobot("watcher", _settings(port, heartbeat_out_address=None), LIMITS)  # reads; no heartbeat
    owner = subprocess.Popen([sys.executable, "-c", MOVING_OWNER, str(port)],
                             cwd=Path(__file__).resolve().parents[2], stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL)
    try:
        watcher.connect()
        y0 = watcher.state().T_base_tool[1, 3]
        wait_for(lambda: watcher.state().T_base_tool[1, 3] - y0 > 0.03, 30.0)  # 0.3 s into the move
        y_kill = watcher.state().T_base_tool[1, 3]
        owner.kill()
        owner.wait(timeout=10)
        wait_for(lambda: watcher.state().metadata["status"] == "error", 1.0 + 1.0)  # the watchdog, plus margin
        y_halt = watcher.state().T_base_tool[1, 3]
        assert y_halt - y_kill < 0.1 * (1.0 + 0.2 + 0.5)  # heartbeat period + watchdog + margin, at 0.1 m/s
        assert y0 + 0.25 - y_halt > 0.05  # short of the target
        time.sleep(0.3)
        assert watcher.state().T_base_tool[1, 3] == y_halt  # frozen
    finally:
        watcher.close()
        if owner.poll() is None:
            owner.kill()
            owner.wait(timeout=10)
