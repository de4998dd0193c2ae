"""``GET /health``: open to all; says the service is up, which devices are available and whether
the store can be used."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from cellctl import __version__
from cellctl.api.deps import CellDep

router = APIRouter(tags=["health"])


@router.get("/health")
def health(cell: CellDep, request: Request) -> dict[str, Any]:
    body: dict[str, Any] = {
        "status": "ok",
        "version": __version__,
        "cell_id": cell.config.cell_id,
        "cameras": {k: s.is_open for k, s in cell.cameras.items()},
        "robots": {k: s.is_open for k, s in cell.robots.items()},
    }
    # The store's state as its last call met it (a damaged store stays reported): no query here.
    services = getattr(request.app.state, "services", None)
    problem = getattr(services.store, "problem", None) if services is not None else None
    body["store"] = {"available": problem is None, "reason": problem}
    if problem:
        body["status"] = "store_unavailable"
    return body
