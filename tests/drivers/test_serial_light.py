"""The serial light controller adapter against the simulated controller over a socat pty pair."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.base import DeviceOperationError, DeviceTimeout, DeviceUnavailable
from drivers.health import DeviceHealth
from drivers.io.serial_light import SerialLightController
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
    peer = PeerProcess("drivers.peers.serial_light", "--port", str(pair.b), *extra, ready_text="ready on").start()
    return peer


@pytest.fixture
def light(pty_pair: SocatPair) -> Iterator[tuple[SerialLightController, PeerProcess]]:
    peer = start_sim(pty_pair)
    ctl = SerialLightController(
        "light0", {"port": str(pty_pair.a), "timeout_s": 0.3, "reconnect_initial_s": 0.1, "reconnect_max_s": 0.4}
    )
    ctl.open()
    try:
        yield ctl, peer
    finally:
        ctl.close()
        peer.stop()


def test_registry_and_settings() -> None:
    assert adapter_class("io", "serial_light") is SerialLightController
    with pytest.raises(ValueError, match="baudrate"):
        SerialLightController.Settings.model_validate({"port": "/dev/ttyUSB0", "baudrate": 12})


def test_intensity_strobe_and_digital_io(light: tuple[SerialLightController, PeerProcess]) -> None:
    ctl, _ = light
    assert ctl.command("VER?") == "LIGHTSIM 1.0 CH=4"
    ctl.set_intensity_percent(2, 50)
    assert ctl.intensity_percent(2) == pytest.approx(100 * 128 / 255)  # 50 % of 255, rounded
    assert ctl.command("GET 2") == "2 128"
    ctl.strobe(1, 500)
    ctl.strobe(1, 200)
    assert ctl.command("CNT? 1") == "1 2"
    ctl.write_output(3, True)
    assert ctl.read_input(3) and ctl.command("GET 3") == "3 255"
    ctl.write_output(3, False)
    assert not ctl.read_input(3)
    with pytest.raises(DeviceOperationError, match="channel 4 is not in 0..3"):
        ctl.set_intensity_percent(4, 10)
    with pytest.raises(DeviceOperationError, match="rejected 'SET 1 999': ERR 3"):
        ctl.command("SET 1 999")
    assert ctl.health().available


def test_read_timeout_peer_killed_and_restarted(
    light: tuple[SerialLightController, PeerProcess], pty_pair: SocatPair
) -> None:
    ctl, peer = light
    ctl.set_intensity_percent(0, 20)
    peer.kill()  # the controller dies; the port stays
    err = answers_within(lambda: ctl.intensity_percent(0), 2.0)
    assert isinstance(err, DeviceTimeout) and "no reply to 'GET 0' within 0.3 s" in str(err)
    assert ctl.health() == DeviceHealth(available=False, reason="no reply to 'GET 0'", outages=1, reconnects=0)
    peer = start_sim(pty_pair)
    try:
        ctl.set_intensity_percent(0, 30)  # recovers with the next command
        assert ctl.intensity_percent(0) == pytest.approx(100 * 76 / 255)
        assert ctl.health().available and ctl.health().outages == 1
    finally:
        peer.stop()


def test_port_disappears_and_returns(light: tuple[SerialLightController, PeerProcess], pty_pair: SocatPair) -> None:
    ctl, peer = light
    ctl.write_output(1, True)
    peer.stop()
    pty_pair.stop()  # the USB adapter is pulled: the device node goes away
    with pytest.raises((DeviceUnavailable, DeviceTimeout)):
        ctl.write_output(1, False)
    with pytest.raises(DeviceUnavailable):
        ctl.write_output(1, False)
    pty_pair.start()
    peer = start_sim(pty_pair)
    try:
        deadline = time.monotonic() + 3.0
        while True:  # reopens by itself once the backoff (<= 0.4 s) allows
            try:
                ctl.write_output(1, True)
                break
            except (DeviceUnavailable, DeviceTimeout):
                assert time.monotonic() < deadline
                time.sleep(0.05)
        assert ctl.read_input(1)
        h = ctl.health()
        assert h.available and h.outages == 1 and h.reconnects >= 1
    finally:
        peer.stop()


def test_malformed_replies(pty_pair: SocatPair) -> None:
    peer = start_sim(pty_pair, "--garbage")
    ctl = SerialLightController("light0", {"port": str(pty_pair.a), "timeout_s": 0.3})
    try:
        ctl.open()
        with pytest.raises(DeviceOperationError, match="malformed reply to 'GET 0'"):
            ctl.intensity_percent(0)
        with pytest.raises(DeviceOperationError, match="malformed|unexpected reply"):
            ctl.set_intensity_percent(0, 10)
    finally:
        ctl.close()
        peer.stop()


def test_port_missing_at_open(tmp_path: Path) -> None:
    with pytest.raises(DeviceUnavailable, match="cannot open serial port"):
        SerialLightController("light0", {"port": str(tmp_path / "nope")}).open()
