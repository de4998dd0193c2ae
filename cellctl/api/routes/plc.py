"""``GET /plc/status`` (viewer): every PLC front end (Modbus, OPC UA, EtherNet/IP, robot socket, and any
other the service runs): enabled, address, connected clients, the last request and its answer, and
the request running now (docs/rest.md). Memory only: answered on the event loop."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.plc.engine import plc_status

router = APIRouter(prefix="/plc", tags=["plc"], route_class=EdgeRoute)


@router.get("/status")
async def get_plc_status(services: ServicesDep, _: Viewer) -> dict[str, Any]:
    return plc_status(services)
