"""Cameras: list, settings, and the newest image as PNG or JPEG."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import cv2
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from cellctl.api.deps import CellDep, Viewer, device_call, slot_or_404
from cellctl.api.errors import ApiError
from cellctl.warmup import READY_WAIT_S, RENDERER, Startup
from drivers.base import Camera, Frame

router = APIRouter(prefix="/cameras", tags=["cameras"])

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
