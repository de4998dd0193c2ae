"""The virtual cell's ground truth over REST: ``GET /sim/truth`` (engineer; 404 without a sim device)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
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


class BeltSpeed(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    speed_mm_s: float = Field(ge=0, le=300, description="the belt's speed along base +x, mm/s (0-300)")
    speed_variation: float | None = Field(None, ge=0, le=0.5, description="a slowly varying belt: the speed swings "
                                                                         "by this fraction (0: steady)")


@router.put("/conveyors/{conveyor_id}/speed")
async def belt_speed(conveyor_id: str, body: BeltSpeed, services: ServicesDep, _: Engineer) -> dict[str, Any]:
    """Set a simulated belt's speed now (the virtual plant's drive; a real belt's is the plant's, not
    cellctl's). 404 for a conveyor the config does not name, 409 for one that is not simulated."""
    cfg = services.config.conveyors.get(conveyor_id)
    if cfg is None:
        raise ApiError(404, "unknown_conveyor", f"no conveyor {conveyor_id!r} in the config; configured: "
                                                f"{sorted(services.config.conveyors)}")
    if cfg.kind != "sim_conveyor":
        raise ApiError(409, "not_simulated", f"conveyor {conveyor_id} is a {cfg.kind}: its speed is the plant's")
    device = await run_in_threadpool(services.cell.conveyor(conveyor_id).ensure_open)
    device.set_speed(body.speed_mm_s, body.speed_variation)  # type: ignore[attr-defined]
    return {"conveyor_id": conveyor_id, "speed_mm_s": body.speed_mm_s, "ticks": device.ticks()}
