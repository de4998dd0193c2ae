"""The virtual cell's ground truth over REST: ``GET /sim/truth`` (engineer; 404 without a sim device)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from cellctl.api.deps import Engineer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.config import sim_settings

router = APIRouter(prefix="/sim", tags=["sim"])

@router.get("/truth")
async def truth(services: ServicesDep, _: Engineer) -> dict[str, Any]:
    """The virtual cell's ground truth now: robot, camera, targets and, in a production scene, every
    part's id, state (in_area, held, placed, dropped), true pose ``T_base_part`` (4x4, m) and image box
    ``roi_px`` ([u, v, w, h], null when not in view), and the place grid that fits the place area."""
    settings = sim_settings(services.config)
    if settings is None:
        raise ApiError(404, "no_sim", f"cell {services.config.cell_id!r} has no simulated device (kind: sim); "
                                      "there is no ground truth to show")
    from drivers.sim.world import world_for

    world = world_for(settings.get("scene"), settings.get("seed"))
    out: dict[str, Any] = await run_in_threadpool(world.truth)
    return out
