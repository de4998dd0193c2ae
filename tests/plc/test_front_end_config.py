"""The EtherNet/IP and robot socket sections of cell.yaml: off and on loopback by default, the IEC 62443 zone
key for a front end that can move the robot on another address, and the request engine's own check."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cellctl.cell import Cell
from cellctl.config import ConfigError, default_config_text, load_config, parse_config
from cellctl.jobs import JobManager
from cellctl.plc.engine import Engine, Kind, Request, plc_status
from cellctl.plc.requests import TEXT_BUSY
from cellctl.services import Services
from cellctl.store import open_store


def config_with(tmp: Path, plc: dict[str, object]) -> dict[str, object]:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    data["plc"] = plc
    return data


def test_every_front_end_is_off_and_on_loopback_by_default() -> None:
    plc = load_config(None).plc
    assert not plc.ethernet_ip.enabled and not plc.robot_socket.enabled
    assert (plc.ethernet_ip.host, plc.ethernet_ip.port) == ("127.0.0.1", 44818)
    assert (plc.robot_socket.host, plc.robot_socket.port, plc.robot_socket.pose_format) == ("127.0.0.1", 5021, "ur")
    assert (plc.robot_socket.idle_timeout_s, plc.robot_socket.max_clients) == (60.0, 4)
    assert plc.modbus.idle_timeout_s == 60.0 and plc.modbus.max_connections_per_address >= 1


def test_motion_beyond_loopback_needs_the_zone_decision(tmp_path: Path) -> None:
    enip = {"ethernet_ip": {"enabled": True, "host": "0.0.0.0"}, "allow_motion": True}
    with pytest.raises(ConfigError, match="plc.allow_motion with plc.ethernet_ip on 0.0.0.0"):
        parse_config(config_with(tmp_path, enip))
    assert parse_config(config_with(tmp_path, {**enip, "insecure_plc_network": True})).plc.ethernet_ip.enabled
    # Without motion, or for the socket (it never moves the robot), no decision is needed.
    parse_config(config_with(tmp_path, {"ethernet_ip": {"enabled": True, "host": "0.0.0.0"}}))
    parse_config(config_with(tmp_path, {"robot_socket": {"enabled": True, "host": "0.0.0.0"}, "allow_motion": True}))
    with pytest.raises(ConfigError, match="plc.robot_socket.pose_format"):
        parse_config(config_with(tmp_path, {"robot_socket": {"pose_format": "staubli"}}))


def test_the_engine_refuses_a_motion_front_end_beyond_loopback_and_a_second_request(tmp_path: Path) -> None:
    config = parse_config(config_with(tmp_path, {"allow_motion": True}))
    services = Services(config, Cell(config), open_store(config), JobManager())
    engine = Engine(services)
    try:
        with pytest.raises(OSError, match="plc.insecure_plc_network"):
            engine.register("ethernet_ip", "10.0.0.5", 44818)
        engine.register("robot_socket", "10.0.0.5", 5021, motion=False)  # the socket does not move the robot
        a, b = engine.register("modbus", "127.0.0.1", 5020), engine.register("opcua", "127.0.0.1", 4840)
        engine._running = ("modbus", Request(Kind.VERIFY))  # a verify from Modbus runs
        refused = engine.submit(b, Request(Kind.PICK, 1)).result(5)
        assert refused.text_index == TEXT_BUSY and "verify request from the modbus front end" in refused.message
        assert engine.submit(a, Request(Kind.IDLE)).result(5).ok  # idle is answered at once
        status = engine.status()
        assert status["busy"] and status["running"]["front_end"] == "modbus"
        assert status["front_ends"]["opcua"]["refused_busy"] == 1
        assert status["front_ends"]["opcua"]["last_answer"]["error_text"] == TEXT_BUSY
        assert status["front_ends"]["ethernet_ip"]["enabled"] is False
        engine._running = None
    finally:
        engine.close()
    # Without any front end running, the status has the same shape, every front end off.
    off = plc_status(services)
    assert set(off["front_ends"]) == {"modbus", "opcua", "ethernet_ip", "robot_socket"}
    assert not any(f["enabled"] for f in off["front_ends"].values())
    services.close()
