"""PLC-native front ends of ``cellctl serve``: a Modbus TCP server and an OPC UA server.

Both are off unless ``plc.modbus.enabled`` / ``plc.opcua.enabled`` in ``cell.yaml``; both run in
their own threads (their own event loops) beside the REST service and share its :class:`Services`.
Register map: docs/plc-modbus.md; address space: docs/plc-opcua.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

from cellctl.config import CellConfig
from cellctl.services import Services

log = logging.getLogger(__name__)

__all__ = ["PlcServers", "preflight", "start_plc_servers"]
"""The request engine every front end shares is ``cellctl.plc.requests`` (``execute_pick``, ``execute_verify``);
the servers ``modbus_server`` and ``opcua_server`` (with OPC UA for Machine Vision's ``VisionSystem``:
``opcua_mv``); production over the PLC ``production``/``opcua_production``."""


class _Server(Protocol):
    def stop(self) -> None: ...


@dataclass
class PlcServers:
    """The PLC servers that were started (stop them in reverse order)."""

    running: list[_Server] = field(default_factory=list)

    def stop(self) -> None:
        while self.running:
            server = self.running.pop()
            try:
                server.stop()
            except Exception:  # noqa: BLE001 - stop every server even when one fails
                log.exception("stopping a PLC server failed")


def preflight(config: CellConfig) -> None:
    """Refuse, with one line (``OSError``), a PLC setup that could not start: run before serving."""
    zone = config.plc.zone_problem()  # the config's own check, again for a config built in code
    if zone:
        raise OSError(zone)
    if config.plc.opcua.enabled:
        from cellctl.plc.opcua_server import security_problem

        problem = security_problem(config.plc.opcua)
        if problem:
            raise OSError(problem)


def start_plc_servers(services: Services) -> PlcServers:
    """Start the servers the config enables; on a failure stop those already started and raise."""
    cfg = services.config.plc
    zone = cfg.zone_problem()
    if zone:
        raise OSError(zone)
    servers = PlcServers()
    try:
        if cfg.modbus.enabled:
            from cellctl.plc.modbus_server import ModbusPlcServer

            m = cfg.modbus
            servers.running.append(ModbusPlcServer(services, m.host, m.port, m.unit_id).start())
        if cfg.opcua.enabled:
            from cellctl.plc.opcua_server import OpcUaPlcServer

            servers.running.append(OpcUaPlcServer(services, cfg.opcua).start())
    except BaseException:
        servers.stop()
        raise
    return servers
