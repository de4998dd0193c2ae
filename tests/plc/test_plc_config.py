"""The ``plc`` section of cell.yaml and starting the servers it names (in process, no devices opened)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from pymodbus.client import ModbusTcpClient

from cellctl.cell import Cell
from cellctl.config import ConfigError, default_config_text, load_config, parse_config
from cellctl.jobs import JobManager
from cellctl.plc import modbus_server as mb
from cellctl.plc import start_plc_servers
from cellctl.services import Services
from cellctl.store import open_store
from tests.conftest import free_port


def config_with(tmp: Path, plc: dict[str, object]) -> dict[str, object]:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    data["plc"] = plc
    return data


@pytest.fixture()
def services(tmp_path: Path) -> Iterator[Services]:
    config = parse_config(config_with(tmp_path, {}))
    svc = Services(config, Cell(config), open_store(config), JobManager())
    try:
        yield svc
    finally:
        svc.close()


def test_the_virtual_cell_keeps_its_plc_servers_off() -> None:
    plc = load_config(None).plc
    assert not plc.modbus.enabled and not plc.opcua.enabled
    assert (plc.modbus.host, plc.modbus.port, plc.modbus.unit_id) == ("127.0.0.1", 5020, 1)
    assert (plc.opcua.port, plc.opcua.security) == (4840, "none")


def test_bad_plc_settings_are_refused_with_the_key(tmp_path: Path) -> None:
    cases: list[tuple[dict[str, object], str]] = [
        ({"modbus": {"enabled": True, "port": 70000}}, "plc.modbus.port"),
        ({"modbus": {"unit": 1}}, "plc.modbus.unit: unknown key"),
        ({"opcua": {"security": "basic128"}}, "plc.opcua.security"),
        ({"opcua": {"enabled": True, "security": "basic256sha256"}}, "needs the server certificate and key"),
    ]
    for plc, message in cases:
        with pytest.raises(ConfigError, match=message):
            parse_config(config_with(tmp_path, plc))


def test_nothing_starts_unless_enabled(services: Services) -> None:
    servers = start_plc_servers(services)
    assert servers.running == []


def test_modbus_server_on_a_taken_port_fails_with_one_clear_line(services: Services) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        server = mb.ModbusPlcServer(services, "127.0.0.1", port)
        with pytest.raises(OSError, match=f"cannot listen on 127.0.0.1:{port}.*plc.modbus.port"):
            server.start()
        server.stop()


def test_modbus_server_starts_and_stops_from_the_config(tmp_path: Path) -> None:
    port = free_port()
    config = parse_config(config_with(tmp_path, {"modbus": {"enabled": True, "port": port, "unit_id": 7}}))
    svc = Services(config, Cell(config), open_store(config), JobManager())
    servers = start_plc_servers(svc)
    try:
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0) as plc:
            r = plc.read_holding_registers(mb.STATUS, count=mb.MAP_VERSION_REG - mb.STATUS + 1, device_id=7)
            assert not r.isError()
            assert r.registers[mb.MAX_PICKS_REG - mb.STATUS] == mb.MAX_PICKS
            assert r.registers[mb.MAP_VERSION_REG - mb.STATUS] == mb.MAP_VERSION
            assert r.registers[mb.ECHO_SEQ - mb.STATUS] == 0  # no answer yet
            beat = r.registers[mb.HEARTBEAT - mb.STATUS]
            time.sleep(0.35)
            later = plc.read_holding_registers(mb.HEARTBEAT, count=1, device_id=7).registers[0]
            assert 2 <= (later - beat) % 65536 <= 60  # counts every 100 ms
    finally:
        servers.stop()
        svc.close()
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0  # the port is free again
