"""Pick guidance over REST: recipes, teach from a live frame, ``POST /pick``, annotated frames."""

from __future__ import annotations

import logging
from typing import Annotated, Any, Literal

import cv2
from fastapi import APIRouter, Path
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.concurrency import run_in_threadpool

from cellctl.api.deps import Engineer, Operator, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.mapping import NoCalibration
from cellctl.pick.flow import PickError, Recipe, run_pick
from cellctl.pick.frames import annotate
from cellctl.pick.model import ModelFileError
from cellctl.store import NotFound

log = logging.getLogger(__name__)
router = APIRouter(tags=["pick"])


class RecipeInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: int = Field(ge=0, le=65535, description="the PLC's recipe number")
    recipe: Recipe


class PickInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: int = Field(ge=0, le=65535)
    camera_id: str | None = None
    move: bool = Field(False, description="pick the best reachable part with the robot (engineer role)")


class TeachInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera_id: str | None = None
    roi: tuple[float, float, float, float] = Field(description="U, V, W, H in pixels; reference point = centre")
    mode: Literal["shape", "blob"] = "shape"
    name: str = Field("part", min_length=1, max_length=64)


def _no_recipe(services: ServicesDep, recipe_id: int) -> str:
    stored = sorted({r.recipe_id for r in services.store.list_recipes()})
    return (f"no recipe {recipe_id} in cell {services.config.cell_id!r}; stored: "
            f"{', '.join(map(str, stored)) or 'none'} (GET /recipes lists them; POST /recipes stores one)")


@router.get("/recipes")
def list_recipes(services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    return [{"recipe_id": r.recipe_id, "version": r.version, "name": r.name, "creator": r.creator,
             "created_s": r.created_s} for r in services.store.list_recipes()]


@router.get("/recipes/{recipe_id}")
def get_recipe(recipe_id: Annotated[int, Path(ge=0, le=65535)], services: ServicesDep, _: Viewer) -> dict[str, Any]:
    try:
        r = services.store.get_recipe(recipe_id)
    except NotFound:
        raise ApiError(404, "unknown_recipe", _no_recipe(services, recipe_id)) from None
    out: dict[str, Any] = r.to_dict()
    return out


@router.post("/recipes", status_code=201)
def save_recipe(body: RecipeInput, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    try:
        body.recipe.part_models()
    except ModelFileError as exc:
        raise ApiError(422, "invalid_model", str(exc)) from None
    r = services.store.save_recipe(body.recipe_id, body.recipe.name, body.recipe.model_dump(mode="json"), who.name)
    services.store.audit(who.name, "recipe.save", str(body.recipe_id), {"version": r.version, "name": r.name}, "ok")
    return {"recipe_id": r.recipe_id, "version": r.version, "name": r.name}


@router.post("/pick/teach")
async def teach(body: TeachInput, services: ServicesDep, _: Engineer) -> dict[str, Any]:
    from cellctl.pick.model import check_roi
    from cellctl.pick.model import teach as teach_model

    cam_id = body.camera_id or services.config.calibration.camera
    if cam_id not in services.cell.cameras:
        raise ApiError(404, "unknown_camera", f"no camera {cam_id!r}")
    frame = await run_in_threadpool(lambda: services.cell.camera(cam_id).ensure_open().grab(timeout_s=5.0))
    try:
        check_roi(body.roi, frame.size)
        model = await run_in_threadpool(teach_model, frame.pixels, body.roi, mode=body.mode, name=body.name)
    except ValueError as exc:
        raise ApiError(422, "cannot_teach", str(exc)) from None
    out: dict[str, Any] = model.to_dict()
    return out


@router.post("/pick")
async def pick(body: PickInput, services: ServicesDep, who: Operator) -> dict[str, Any]:
    if body.move and not who.has("engineer"):
        raise ApiError(403, "forbidden", f"move: true moves the robot and needs the engineer role; token "
                                         f"{who.name!r} has {who.role}")
    try:
        answer: dict[str, Any] = await run_in_threadpool(run_pick, services, body.recipe_id, body.camera_id,
                                                         body.move, who.name)
    except NotFound:
        raise ApiError(404, "unknown_recipe", _no_recipe(services, body.recipe_id)) from None
    except NoCalibration as exc:
        raise ApiError(409, "no_active_calibration", str(exc)) from None
    except (PickError, ModelFileError, ValidationError) as exc:
        raise ApiError(422, "cannot_pick", str(exc)) from None
    log.info("pick recipe %d: %d picks, trigger-to-answer %.1f ms", body.recipe_id, len(answer["picks"]),
             answer["latency_ms"]["total"])
    return answer


@router.get("/frames/{frame_id}.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def frame_png(frame_id: Annotated[int, Path(ge=1, le=2**62)], services: ServicesDep, _: Viewer) -> Response:
    try:
        f = services.frames.get(frame_id)
    except KeyError as exc:
        raise ApiError(404, "unknown_frame", str(exc.args[0])) from None
    ok, buf = cv2.imencode(".png", annotate(f))
    if not ok:
        raise ApiError(500, "encode_failed", "the frame could not be encoded")
    return Response(buf.tobytes(), media_type="image/png", headers={"Cache-Control": "no-store"})
