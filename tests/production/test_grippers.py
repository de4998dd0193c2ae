"""The production gripper actions against real peers: the Robotiq 2F peer (Modbus RTU over a pty
pair) and a vacuum cup / parallel gripper on Modbus TCP digital I/O (``drivers.peers.modbus_gripper``)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell import Cell
from cellctl.config import parse_config
from cellctl.jobs import JobManager
from cellctl.pick.recipe import GripperSettings, PickError
from cellctl.production.config import GripperDevice
from cellctl.production.gripper import Gripper
from cellctl.services import Services
from cellctl.store import open_store
from drivers.peers.modbus_gripper import ModbusGripperSim
from tests.drivers.peers import PeerProcess, SocatPair, free_port


def services_with(tmp: Path, io: dict[str, Any]) -> Services:
    config = parse_config({"format_version": 1, "cell_id": "grippers", "store": {"path": str(tmp / "cell.db")},
                           "cameras": {}, "robots": {}, "io": io})
    return Services(config, Cell(config), open_store(config), JobManager())


@pytest.fixture
def robotiq(tmp_path: Path) -> Iterator[Services]:
    pair = SocatPair(tmp_path).start()
    peer = PeerProcess("drivers.peers.robotiq_gripper", "--port", str(pair.b), "--object-at", "200",
                       ready_text="gripper simulator on").start()
    svc = services_with(tmp_path, {"grip": {"kind": "robotiq_gripper",
                                            "settings": {"port": str(pair.a), "timeout_s": 2.0}}})
    try:
        yield svc
    finally:
        svc.close()
        peer.stop()
        pair.stop()


def robotiq_settings(**kw: Any) -> GripperSettings:
    return GripperSettings(settle_s=0.02, device=GripperDevice(io_id="grip", kind="robotiq_2f"), **kw)


def test_robotiq_holds_checks_the_width_and_releases(robotiq: Services) -> None:
    # The peer's object sits at position 200 of 255: 85 * (1 - 200/255) = 18.3 mm between the fingers.
    g = Gripper(robotiq, robotiq_settings(grip_width_mm=18.3))
    g.open()
    check = g.close_and_check()
    assert check.held and check.width_mm == pytest.approx(18.3, abs=0.5), check
    assert g.holding()
    assert g.release() >= 0.1 and not g.holding()
    wrong = Gripper(robotiq, robotiq_settings(grip_width_mm=30.0)).close_and_check()
    assert not wrong.held and "18.3 mm, not 30.0" in wrong.detail, wrong


def test_a_recipe_gripper_on_a_device_that_is_not_configured_is_refused(robotiq: Services) -> None:
    with pytest.raises(PickError, match="not a configured io device"):
        Gripper(robotiq, GripperSettings(device=GripperDevice(io_id="nope", kind="robotiq_2f")))


@pytest.fixture
def dio(tmp_path: Path) -> Iterator[tuple[Services, ModbusGripperSim]]:
    port = free_port()
    sim = ModbusGripperSim(port=port, rise_s=0.05).start()
    svc = services_with(tmp_path, {"block": {"kind": "modbus", "settings": {"host": "127.0.0.1", "port": port,
                                                                            "timeout_s": 2.0}}})
    try:
        yield svc, sim
    finally:
        svc.close()
        sim.stop()


@pytest.mark.parametrize("device", [
    {"io_id": "block", "kind": "vacuum", "output": 0, "open_output": 1, "input": 0, "input_timeout_s": 0.5},
    {"io_id": "block", "kind": "parallel", "output": 2, "open_output": 3, "input": 1, "input_timeout_s": 0.5},
])
def test_digital_io_grippers_check_their_input(dio: tuple[Services, ModbusGripperSim], device: dict[str, Any]) -> None:
    svc, sim = dio
    g = Gripper(svc, GripperSettings(settle_s=0.0, device=GripperDevice.model_validate(device)))
    g.open()
    assert not g.holding()
    check = g.close_and_check()
    assert check.held and check.width_mm is None, check
    assert g.holding()
    g.release()
    assert not g.holding()
    sim.set_part(False)  # nothing under the gripper: the input never comes
    empty = g.close_and_check()
    assert not empty.held and f"input {device['input']}" in empty.detail and empty.elapsed_s >= 0.5
    g.open()


def test_a_digital_io_gripper_needs_its_channels() -> None:
    with pytest.raises(ValueError, match="vacuum switch"):
        GripperDevice.model_validate({"io_id": "block", "kind": "vacuum", "output": 0})
