"""PLC-native front ends of ``cellctl serve``: Modbus TCP, OPC UA, EtherNet/IP and the robot socket.

Each is off unless ``plc.<front end>.enabled`` in ``cell.yaml``; each runs in its own thread (its own
event loop) beside the REST service, shares its :class:`Services`, and runs every request through
the one request engine (:mod:`cellctl.plc.engine`). Register map: docs/plc-modbus.md; address
space: docs/plc-opcua.md; tags: docs/plc-ethernet-ip.md; line protocol: docs/robot-socket.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

from cellctl.config import CellConfig
from cellctl.services import Services

log = logging.getLogger(__name__)

__all__ = ["PlcServers", "preflight", "start_plc_servers"]
"""The request engine every front end shares is ``cellctl.plc.engine`` (``Request``, ``Kind``,
``Engine.submit``; ``services.plc_engine``), over the request functions of ``cellctl.plc.requests`` and
``production``; the servers ``modbus_server``, ``opcua_server`` (with OPC UA for Machine Vision's
``VisionSystem``: ``opcua_mv``), ``enip_server``, ``robot_socket``; the Modbus register table ``modbus_map``."""


class _Server(Protocol):
    def stop(self) -> None: ...


@dataclass
class PlcServers:
    """The PLC servers that were started (stop them in reverse order, then the request engine)."""

    running: list[_Server] = field(default_factory=list)
    services: Services | None = None

    def stop(self) -> None:
        while self.running:
            server = self.running.pop()
            try:
                server.stop()
            except Exception:  # noqa: BLE001 - stop every server even when one fails
                log.exception("stopping a PLC server failed")
        if self.services is not None:
            from cellctl.plc.engine import forget_engine

            forget_engine(self.services)


def preflight(config: CellConfig) -> None:
    """Refuse, with one line (``OSError``), a PLC setup that could not start: run before serving."""
    zone = config.plc.zone_problem()  # the config's own check, again for a config built in code
    if zone:
        raise OSError(zone)
    if config.plc.opcua.enabled:
        from cellctl.plc.opcua_security import security_problem

        problem = security_problem(config.plc.opcua)
        if problem:
            raise OSError(problem)


def start_plc_servers(services: Services) -> PlcServers:
    """Start the servers the config enables; on a failure stop those already started and raise."""
    cfg = services.config.plc
    zone = cfg.zone_problem()
    if zone:
        raise OSError(zone)
    servers = PlcServers(services=services)
    try:
        if cfg.modbus.enabled:
            from cellctl.plc.modbus_server import ModbusPlcServer

            m = cfg.modbus
            servers.running.append(ModbusPlcServer(services, m.host, m.port, m.unit_id, config=m).start())
        if cfg.opcua.enabled:
            from cellctl.plc.opcua_server import OpcUaPlcServer

            servers.running.append(OpcUaPlcServer(services, cfg.opcua).start())
        if cfg.ethernet_ip.enabled:
            from cellctl.plc.enip_server import EthernetIpServer

            servers.running.append(EthernetIpServer(services, cfg.ethernet_ip).start())
        if cfg.robot_socket.enabled:
            from cellctl.plc.robot_socket import RobotSocketServer

            servers.running.append(RobotSocketServer(services, cfg.robot_socket).start())
    except BaseException:
        servers.stop()
        raise
    return servers
