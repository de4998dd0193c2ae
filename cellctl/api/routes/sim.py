"""The virtual cell over REST: its ground truth (``GET /sim/truth``) and faults on request
(``POST /sim/faults``: the camera bumped or drifting, docs/drift.md); engineer; 404 without a sim device."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from cellctl.api.deps import Engineer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.config import sim_settings
from cellctl.strict_types import Num

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


Shift = Annotated[Num, Field(ge=-100.0, le=100.0)]
Turn = Annotated[Num, Field(ge=-10.0, le=10.0)]


class FaultsInput(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    camera_shift_mm: tuple[Shift, Shift, Shift] = Field(
        (0.0, 0.0, 0.0), description="the camera's shift along the base frame's x, y, z from its nominal pose, mm "
                                     "(each within +-100)")
    camera_rot_deg: tuple[Turn, Turn, Turn] = Field(
        (0.0, 0.0, 0.0), description="the camera's turn about the base frame's x, y, z axes (about its own centre), "
                                     "degrees (each within +-10)")
    ramp_s: Num = Field(0.0, ge=0, le=86400, description="reach it linearly over this many seconds from the "
                           "fault in force (a slow thermal drift); 0: at once")


@router.post("/faults")
async def faults(body: FaultsInput, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Bump the simulated camera: a shift along and a turn about the base frame's axes applied to its true pose
    (every calibration stays as it was); ``{"camera_shift_mm": [0, 0, 0], "camera_rot_deg": [0, 0, 0]}`` puts
    it back. Answers the fault in force and its target."""
    settings = _sim_camera_settings(services)
    from drivers.sim.camera_fault import Fault
    from drivers.sim.world import world_for

    world = world_for(settings.get("scene"), settings.get("seed"))
    fault = Fault(tuple(float(v) for v in body.camera_shift_mm), tuple(float(v) for v in body.camera_rot_deg))  # type: ignore[arg-type]
    world.camera_fault.set(fault, float(body.ramp_s))
    services.store.audit(who.name, "sim.faults", "camera", body.model_dump(mode="json"), "set")
    return world.camera_fault.state()


def _sim_camera_settings(services: Any) -> dict[str, Any]:
    for cam in services.config.cameras.values():
        if cam.kind == "sim":
            return dict(cam.settings)
    raise ApiError(404, "no_sim_camera", f"cell {services.config.cell_id!r} has no simulated camera (kind: sim); "
                                         "there is no camera to bump")
