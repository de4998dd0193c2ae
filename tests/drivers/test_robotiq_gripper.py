"""The Robotiq gripper adapter against the simulated gripper (pymodbus RTU) over a socat pty pair."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from drivers.base import DeviceOperationError, DeviceTimeout, DeviceUnavailable
from drivers.io.robotiq_gripper import RobotiqGripper
from drivers.registry import adapter_class
from tests.drivers.peers import PeerProcess, SocatPair, answers_within


@pytest.fixture
def pty_pair(tmp_path: Path) -> Iterator[SocatPair]:
    pair = SocatPair(tmp_path).start()
    try:
        yield pair
    finally:
        pair.stop()


def start_sim(pair: SocatPair, *extra: str) -> PeerProcess:
    peer = PeerProcess(
        "drivers.peers.robotiq_gripper", "--port", str(pair.b), *extra, ready_text="gripper simulator on"
    ).start()
    return peer


def settings(pair: SocatPair, **kw: object) -> dict[str, object]:
    # 2 s per read: the peer is a Python process that a loaded CI machine (4 workers on 2 cores) may
    # keep from answering for more than the 0.3 s used before (a status read timed out in CI)
    return {"port": str(pair.a), "timeout_s": 2.0, "reconnect_initial_s": 0.1, "reconnect_max_s": 0.4, **kw}


@pytest.fixture
def gripper(pty_pair: SocatPair) -> Iterator[tuple[RobotiqGripper, PeerProcess]]:
    peer = start_sim(pty_pair)
    g = RobotiqGripper("grip0", settings(pty_pair))
    try:
        g.open()
        yield g, peer
    finally:
        g.close()
        peer.stop()


def test_registry_and_settings() -> None:
    assert adapter_class("io", "robotiq_gripper") is RobotiqGripper
    with pytest.raises(ValueError, match="force_percent"):
        RobotiqGripper.Settings.model_validate({"port": "/dev/ttyUSB0", "force_percent": 120})


def test_activate_grip_object_and_open(gripper: tuple[RobotiqGripper, PeerProcess]) -> None:
    g, _ = gripper
    s = g.status()
    assert s["activated"] and s["fault"] == 0
    t0 = time.monotonic()
    s = g.close_gripper(speed_percent=50, force_percent=40)
    elapsed = time.monotonic() - t0
    # the object sits at position 200: the fingers stop there and report it while closing
    assert s["object_detected"] and s["position"] == 200 and s["position_request"] == 255
    assert s["current"] == round(0.4 * 255) // 2
    assert 0.5 < elapsed < 2.5  # 200 units at 100 + 1.5 x 128 units/s = 0.68 s
    assert g.read_input(0)
    g.write_output(0, False)
    s = g.status()
    assert s["at_position"] and s["position"] == 0 and not g.read_input(0)
    assert g.move(120)["position"] == 120
    with pytest.raises(DeviceOperationError, match="one output"):
        g.write_output(1, True)


def test_no_object_and_move_before_activation(pty_pair: SocatPair) -> None:
    peer = start_sim(pty_pair, "--object-at", "-1")
    g = RobotiqGripper("grip0", settings(pty_pair, activate_on_open=False))
    try:
        g.open()
        assert not g.status()["activated"]
        with pytest.raises(DeviceOperationError, match="fault 0x05 action delayed: the activation must complete first"):
            g.move(255)
        g.activate()
        s = g.close_gripper()
        assert s["at_position"] and s["position"] == 255 and not s["object_detected"]
    finally:
        g.close()
        peer.stop()


def test_read_timeout_peer_killed_and_restarted(
    gripper: tuple[RobotiqGripper, PeerProcess], pty_pair: SocatPair
) -> None:
    g, peer = gripper
    peer.kill()
    err = answers_within(g.status, 3.0)
    assert isinstance(err, DeviceTimeout) and "did not answer the status read within 2.0 s" in str(err)
    assert g.health().available is False and g.health().outages == 1
    peer = start_sim(pty_pair)
    try:
        deadline = time.monotonic() + 8.0
        while True:  # recovers by itself on the next calls (reopen backoff <= 0.4 s)
            try:
                g.activate()  # a restarted gripper must be activated again
                break
            except (DeviceUnavailable, DeviceTimeout):
                assert time.monotonic() < deadline
                time.sleep(0.05)
        assert g.close_gripper()["object_detected"]
        assert g.health().available and g.health().outages == 1
    finally:
        peer.stop()


def test_port_disappears(gripper: tuple[RobotiqGripper, PeerProcess], pty_pair: SocatPair) -> None:
    g, peer = gripper
    peer.stop()
    pty_pair.stop()
    with pytest.raises((DeviceUnavailable, DeviceTimeout)):
        g.status()
    with pytest.raises(DeviceUnavailable):
        g.status()
    pty_pair.start()
    peer = start_sim(pty_pair)
    try:
        deadline = time.monotonic() + 8.0
        while True:
            try:
                g.status()
                break
            except (DeviceUnavailable, DeviceTimeout):
                assert time.monotonic() < deadline
                time.sleep(0.05)
        assert g.health().reconnects >= 1 and g.health().outages == 1
    finally:
        peer.stop()


def test_malformed_replies(pty_pair: SocatPair) -> None:
    stop = threading.Event()

    def garbage() -> None:
        with serial.Serial(str(pty_pair.b), 115200, timeout=0.05) as port:
            while not stop.is_set():
                if port.read(64):
                    port.write(b"\x09\x04\x06garbage-not-a-crc\xff")

    th = threading.Thread(target=garbage, daemon=True)
    th.start()
    g = RobotiqGripper("grip0", settings(pty_pair, activate_on_open=False))
    try:
        g.open()
        err = answers_within(g.status, 3.0)
        assert isinstance(err, (DeviceTimeout, DeviceOperationError, DeviceUnavailable)), repr(err)
        assert g.health().available is False
    finally:
        g.close()
        stop.set()
        th.join(timeout=2)
