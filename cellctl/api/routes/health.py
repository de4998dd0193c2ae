"""``GET /health``: open to all; says the service is up and which devices are available."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from cellctl import __version__
from cellctl.api.deps import CellDep

router = APIRouter(tags=["health"])


@router.get("/health")
def health(cell: CellDep) -> dict[str, Any]:
    return {
        "status": "ok",
        "version": __version__,
        "cell_id": cell.config.cell_id,
        "cameras": {k: s.is_open for k, s in cell.cameras.items()},
        "robots": {k: s.is_open for k, s in cell.robots.items()},
    }
