"""Cameras: list, settings, and the newest image as PNG or JPEG."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import cv2
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import CellDep, Engineer, Viewer, device_call, slot_or_404
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.camera_controls import ControlRefused, apply_controls, controls_of
from cellctl.strict_types import Num
from cellctl.warmup import READY_WAIT_S, RENDERER, Startup
from drivers.base import Camera, Frame

router = APIRouter(prefix="/cameras", tags=["cameras"], route_class=EdgeRoute)

CAMERA_TIMEOUT_S = 5.0
"""A frame may take a while (exposure, a virtual render); past this the camera is unavailable. The
clock starts after the service's own start-up work for cameras (``cellctl.warmup``): compiling the
renderer is never counted as the camera's time."""


def _slot(cell: CellDep, camera_id: str) -> Any:
    return slot_or_404(cell.cameras, "camera", camera_id)


@router.get("")
def list_cameras(cell: CellDep, _: Viewer) -> list[dict[str, Any]]:
    return [slot.status() for slot in cell.cameras.values()]


@router.get("/{camera_id}/settings")
async def camera_settings(camera_id: str, cell: CellDep, _: Viewer) -> dict[str, Any]:
    slot = _slot(cell, camera_id)
    settings: dict[str, Any] = await device_call(slot, lambda cam: cam.settings())
    return {"id": camera_id, "kind": slot.kind, **settings}


@router.get("/{camera_id}/controls")
async def get_controls(camera_id: str, cell: CellDep, _: Viewer) -> dict[str, Any]:
    """Exposure (us), gain (dB) and trigger mode: each ``supported`` or not (``why``), its value and bounds."""
    slot = _slot(cell, camera_id)
    controls: dict[str, Any] = await device_call(slot, lambda cam: controls_of(cam, slot.kind))
    return {"camera_id": camera_id, "kind": slot.kind, "controls": controls}


class ControlsInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    exposure_us: Num | None = Field(None, gt=0, le=60_000_000, description="exposure time, microseconds")
    gain_db: Num | None = Field(None, ge=-100, le=100, description="gain, decibels")
    trigger: Literal["free_run", "software", "hardware"] | None = None


@router.put("/{camera_id}/controls")
async def put_controls(camera_id: str, body: ControlsInput, cell: CellDep, services: ServicesDep,
                       who: Engineer) -> dict[str, Any]:
    """Set the given controls (checked against the camera's bounds first: all or none); audited
    ``camera.controls`` with the values before and after."""
    slot = _slot(cell, camera_id)
    changes = body.model_dump(exclude_none=True)
    if not changes:
        raise ApiError(422, "invalid_request", "give at least one of exposure_us, gain_db, trigger")
    before: dict[str, Any] = await device_call(slot, lambda cam: controls_of(cam, slot.kind))
    old = {k: before[k]["value"] for k in changes}
    try:
        after: dict[str, Any] = await device_call(slot, lambda cam: apply_controls(cam, slot.kind, camera_id, changes))
    except ControlRefused as exc:
        services.store.audit(who.name, "camera.controls", f"camera:{camera_id}", {"set": changes, "before": old},
                             f"refused: {exc}")
        raise ApiError(422, exc.code, str(exc)) from None
    services.store.audit(who.name, "camera.controls", f"camera:{camera_id}",
                         {"set": changes, "before": old, "after": {k: after[k]["value"] for k in changes}}, "ok")
    return {"camera_id": camera_id, "kind": slot.kind, "controls": after}


@router.get("/{camera_id}/image", response_class=Response,
            responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}, 503: {}})
async def camera_image(
    camera_id: str, request: Request, cell: CellDep, _: Viewer,
    format: Annotated[Literal["png", "jpeg"] | None, Query(description="png or jpeg; default by Accept")] = None,
) -> Response:
    slot = _slot(cell, camera_id)
    fmt = format or ("jpeg" if "image/jpeg" in request.headers.get("accept", "") else "png")

    def grab(cam: Camera) -> Frame:
        return cam.grab(timeout_s=2.5)

    startup: Startup = request.app.state.startup
    if not await startup.wait_async(RENDERER, READY_WAIT_S):  # held, not refused: a first grab after start works
        waiting = ", ".join(startup.waiting_for())
        raise ApiError(503, "starting", f"the service is still starting (waiting for {waiting} after "
                                        f"{READY_WAIT_S:.0f} s); try again shortly")
    frame: Frame = await device_call(slot, grab, timeout_s=CAMERA_TIMEOUT_S)
    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", frame.pixels)
    if not ok:
        raise ApiError(502, "encode_failed", f"camera {camera_id}: the frame could not be encoded as {fmt}")
    return Response(
        content=buf.tobytes(),
        media_type=f"image/{fmt}",
        headers={"X-Frame-Id": str(frame.frame_id), "X-Timestamp-S": repr(frame.timestamp_s),
                 "Cache-Control": "no-store"},
    )
