"""The ``plc`` section of cell.yaml and starting the servers it names (in process, no devices opened)."""

from __future__ import annotations

import re
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


ZONE = "plc.insecure_plc_network: true"


@pytest.mark.parametrize("plc", [
    {"opcua": {"enabled": True, "host": "0.0.0.0"}},
    {"opcua": {"enabled": True, "host": "192.168.10.5", "security": "none"}, "allow_motion": False},
    {"opcua": {"enabled": True, "host": "plc-net.example"}},  # a name may resolve to anything
    {"modbus": {"enabled": True, "host": "192.168.10.5"}, "allow_motion": True},
    {"modbus": {"enabled": True, "host": "::"}, "allow_motion": True},
])
def test_an_unauthenticated_server_beyond_loopback_needs_the_zone_decision(tmp_path: Path,
                                                                           plc: dict[str, object]) -> None:
    """OPC UA without security, or Modbus that may move the robot, off loopback: refused at load,
    naming the key and the IEC 62443 zone decision; accepted once the config records it."""
    key = "plc.opcua.security none" if "opcua" in plc else "plc.allow_motion with plc.modbus"
    with pytest.raises(ConfigError, match=f"{key} on .*not loopback.*IEC 62443 zone.*{ZONE}"):
        parse_config(config_with(tmp_path, plc))
    cfg = parse_config(config_with(tmp_path, {**plc, "insecure_plc_network": True}))
    assert cfg.plc.insecure_plc_network and cfg.plc.zone_problem() is None


@pytest.mark.parametrize("plc", [
    {"opcua": {"enabled": True, "host": "127.0.0.1"}, "allow_motion": True},
    {"opcua": {"enabled": True, "host": "::1"}},
    {"opcua": {"enabled": True, "host": "localhost"}},
    {"opcua": {"enabled": False, "host": "0.0.0.0"}},  # not served: nothing exposed
    {"opcua": {"enabled": True, "host": "0.0.0.0", "security": "basic256sha256", "cert": "c.pem", "key": "k.pem",
               "trusted_client_certs": "trusted"}, "allow_motion": True},
    {"modbus": {"enabled": True, "host": "127.0.0.2"}, "allow_motion": True},
    {"modbus": {"enabled": True, "host": "192.168.10.5"}},  # no motion: picks and verify only (warned)
    {"modbus": {"enabled": False, "host": "192.168.10.5"}, "allow_motion": True},
])
def test_loopback_secured_or_motionless_servers_need_no_zone_decision(tmp_path: Path,
                                                                      plc: dict[str, object]) -> None:
    cfg = parse_config(config_with(tmp_path, plc))
    assert not cfg.plc.insecure_plc_network and cfg.plc.zone_problem() is None


def test_the_zone_check_also_holds_for_a_config_built_in_code(services: Services) -> None:
    """A config changed with model_copy skips pydantic's validators: the servers still refuse to start."""
    plc = services.config.plc.model_copy(update={
        "allow_motion": True, "modbus": services.config.plc.modbus.model_copy(update={
            "enabled": True, "host": "192.168.10.5", "port": free_port()})})
    unsafe = Services(services.config.model_copy(update={"plc": plc}), services.cell, services.store, services.jobs)
    with pytest.raises(OSError, match=f"plc.allow_motion with plc.modbus on 192.168.10.5.*{ZONE}"):
        start_plc_servers(unsafe)
    from cellctl.plc import preflight

    with pytest.raises(OSError, match=ZONE):
        preflight(unsafe.config)


def test_serve_refuses_to_start_without_the_zone_decision(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cellctl.cli import main

    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(config_with(tmp_path, {"opcua": {"enabled": True, "host": "0.0.0.0"}})))
    assert main(["serve", "--config", str(path), "--port", str(free_port())]) == 2
    err = capsys.readouterr().err
    assert "plc.opcua.security none on 0.0.0.0" in err and ZONE in err
    assert not (tmp_path / "cell.db").exists()  # refused before anything was opened


@pytest.mark.parametrize("page", ["plc-modbus.md", "plc-opcua.md"])
def test_the_docs_plc_sections_parse(tmp_path: Path, page: str) -> None:
    """Every ``plc:`` example of the PLC pages is a valid config (the zone decision ones included)."""
    from tests.conftest import REPO

    blocks = re.findall(r"```yaml\n(.*?)```", (REPO / "docs" / page).read_text(), flags=re.S)
    sections = [yaml.safe_load(b)["plc"] for b in blocks if b.startswith("plc:")]
    assert any(s.get("insecure_plc_network") for s in sections)
    for plc in sections:
        parse_config(config_with(tmp_path, plc))
