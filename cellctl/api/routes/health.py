"""``GET /health``: open to all; says the service is up, whether its start-up work is done
(``starting`` with what it is ``waiting_for``, then ``ok``: ``cellctl.warmup``) and which devices
are available, and whether the store can be used (``store_unavailable`` when it cannot). Always 200
while the service answers: the status is in the body."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from cellctl import __version__
from cellctl.api.deps import CellDep
from cellctl.warmup import Startup

router = APIRouter(tags=["health"])


@router.get("/health")
async def health(cell: CellDep, request: Request) -> dict[str, Any]:
    # Async on purpose: in-memory reads only, answered on the event loop with no worker thread,
    # so a flood that holds every worker thread cannot delay it (cellctl.api.pools).
    startup: Startup = request.app.state.startup
    waiting = startup.waiting_for()
    body: dict[str, Any] = {
        "status": "starting" if waiting else "ok",
        "version": __version__,
        "cell_id": cell.config.cell_id,
        "cameras": {k: s.is_open for k, s in cell.cameras.items()},
        "robots": {k: s.is_open for k, s in cell.robots.items()},
    }
    if waiting:
        body["waiting_for"] = waiting
    else:
        body["ready_after_s"] = round(startup.ready_after_s or 0.0, 2)
    if startup.failed():
        body["warm_up_failed"] = startup.failed()
    # The store's state as its last call met it (a damaged store stays reported): no query here.
    services = getattr(request.app.state, "services", None)
    problem = getattr(services.store, "problem", None) if services is not None else None
    body["store"] = {"available": problem is None, "reason": problem}
    if problem:  # a store that is down outranks a warm-up still running: it needs an engineer
        body["status"] = "store_unavailable"
    return body
