"""Pick guidance over REST: recipes, teach from a live frame, ``POST /pick``, annotated frames."""

from __future__ import annotations

import logging
import math
from typing import Annotated, Any, Literal

import cv2
from fastapi import APIRouter, Path, Query
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.concurrency import run_in_threadpool

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Engineer, Operator, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.arm_view import arm_view_now
from cellctl.mapping import NoCalibration
from cellctl.pick.flow import PickError, Recipe, run_pick
from cellctl.pick.frames import annotate
from cellctl.pick.grasp_view import taught_grasps
from cellctl.pick.model import ModelFileError, colour_mode
from cellctl.pick.pose import UnusableCalibration
from cellctl.pick.recipe_limits import RecipeOutsideCell, check_recipe_for_cell
from cellctl.store import NotFound
from cellctl.strict_types import Bool, Count, Num

log = logging.getLogger(__name__)
router = APIRouter(tags=["pick"], route_class=EdgeRoute)


RoiPx = Annotated[Num, Field(ge=-1e5, le=1e5)]


class RecipeInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: Count = Field(ge=0, le=65535, description="the PLC's recipe number")
    recipe: Recipe


class PickInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: Count = Field(ge=0, le=65535)
    camera_id: str | None = None
    move: Bool = Field(False, description="pick the best reachable part with the robot (engineer role)")


class TeachInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera_id: str | None = None
    roi: tuple[RoiPx, RoiPx, RoiPx, RoiPx] = Field(description="U, V, W, H in pixels; reference point = centre")
    mode: Literal["shape", "blob"] = "shape"
    name: str = Field("part", min_length=1, max_length=64)
    colour: Literal["grey", "chroma", "auto"] | None = Field(
        None, description="shape: the channel of a colour frame the model is made of: auto (the default: chroma "
        "when the part's colour edges are strong enough, else grey; a grey camera's frame is always grey), grey "
        "(the grey value) or chroma (the part's colour edges, the background's shading left out; a colour camera "
        "needed)")
    more_rois: list[tuple[RoiPx, RoiPx, RoiPx, RoiPx]] = Field(
        default_factory=list, max_length=4, description="shape: up to 4 more boxes around other instances of the "
                                                        "same part in the frame: the model keeps the edges seen in all")
    refine: Literal["rim"] | None = Field(
        None, description="shape: rim: a round part reports its rim's centre and 1-sigma at every match "
                          "(422 not_round when the part is not round)")


def _no_recipe(services: ServicesDep, recipe_id: int) -> str:
    stored = sorted({r.recipe_id for r in services.store.list_recipes()})
    return (f"no recipe {recipe_id} in cell {services.config.cell_id!r}; stored: "
            f"{', '.join(map(str, stored)) or 'none'} (GET /recipes lists them; POST /recipes stores one)")


@router.get("/recipes")
def list_recipes(services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    """The version in force of every recipe, with its place kind and gripper device (null: none)."""
    return [{"recipe_id": r.recipe_id, "version": r.version, "name": r.name, "creator": r.creator,
             "created_s": r.created_s, "place": (r.data.get("place") or {}).get("kind"),
             "gripper_device": ((r.data.get("gripper") or {}).get("device") or {}).get("io_id")}
            for r in services.store.list_recipes()]


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
    problem = _grasp_problem(body.recipe) or _grasp_on_part(services, body.recipe)
    if problem:
        raise ApiError(422, "invalid_grasp", problem)
    try:
        check_recipe_for_cell(body.recipe, services.config)
    except RecipeOutsideCell as exc:
        raise ApiError(422, "recipe_outside_cell", str(exc)) from None
    # The store audits the save in the same transaction (recipe.save, recipe:<id>): once, never here again.
    r = services.store.save_recipe(body.recipe_id, body.recipe.name, body.recipe.model_dump(mode="json"), who.name)
    return {"recipe_id": r.recipe_id, "version": r.version, "name": r.name}


def _grasp_problem(recipe: Recipe) -> str | None:
    """A parallel gripper (``robotiq_2f``) asked to open or grip wider than its fingers' stroke: the grip
    can never happen as set (the gripper would stop at its stroke and the grip check would fail)."""
    device = recipe.gripper.device
    if device is None or device.kind != "robotiq_2f":
        return None
    for key in ("open_width_mm", "grip_width_mm"):
        width = getattr(recipe.gripper, key)
        if width is not None and width > device.stroke_mm:
            return (f"recipe.gripper.{key} {width:g} mm is wider than the gripper's stroke "
                    f"(gripper.device.stroke_mm {device.stroke_mm:g} mm): its fingers cannot open that far; "
                    "set a width within the stroke, or the device's real stroke")
    return None


def _grasp_on_part(services: ServicesDep, recipe: Recipe) -> str | None:
    """A parallel gripper's grasp that closes on no part material, on more than its stroke, or on a width
    its grip check refuses, at each model's teach pose (``cellctl.pick.grasp_view``); None: none of these,
    or no calibration to draw the grasp with (a vacuum cup has no closing line)."""
    device = recipe.gripper.device
    if device is None or device.kind not in ("robotiq_2f", "parallel"):
        return None
    views, _ = taught_grasps(services, recipe)
    return next((f"recipe.models[{k}]: {v.problem}" for k, v in enumerate(views) if v.problem), None)


class GraspInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe: Recipe


@router.post("/pick/grasp")
def grasp_preview(body: GraspInput, services: ServicesDep, _: Viewer) -> dict[str, Any]:
    """The recipe's grasp drawn at each model's teach pose (image pixels: the gripper centre, the open
    fingers, where they meet the part, the width they close on) and its problem, the one ``POST /recipes``
    refuses with 422 ``invalid_grasp`` for a parallel gripper; ``unavailable`` says why nothing is drawn."""
    try:
        body.recipe.part_models()
    except ModelFileError as exc:
        raise ApiError(422, "invalid_model", str(exc)) from None
    views, why = taught_grasps(services, body.recipe)
    stroke = _grasp_problem(body.recipe)
    return {"grasps": [v.as_json() for v in views], "unavailable": why,
            "problem": stroke or next((f"recipe.models[{k}]: {v.problem}" for k, v in enumerate(views) if v.problem),
                                      None)}


@router.post("/pick/teach")
async def teach(body: TeachInput, services: ServicesDep, _: Engineer,
                preview: Annotated[bool, Query(description="also answer 'preview': the model's edge segments "
                                                            "at the teach pose (image px) to draw on the frame, "
                                                            "and its summary")] = False) -> dict[str, Any]:
    """Teach a part model from the region ``roi`` of a live frame; the answer is the model (a
    recipe's ``models`` entry). The ROI's centre is the reference point; picks report the part's
    yaw relative to this frame (counter-clockwise on screen)."""
    from cellctl.pick.model import NotRoundPart, check_roi
    from cellctl.pick.model import teach as teach_model
    from vision.shape import TeachParams

    cam_id = body.camera_id or services.config.calibration.camera
    if cam_id not in services.cell.cameras:
        raise ApiError(404, "unknown_camera", f"no camera {cam_id!r}")
    frame = await run_in_threadpool(lambda: services.cell.camera(cam_id).ensure_open().grab(timeout_s=5.0))
    arm = await run_in_threadpool(arm_view_now, services, cam_id)
    share = arm.share_of(body.roi) if arm is not None else 0.0
    if arm is not None and share > 0.0:
        # A model taught on the arm's image finds the arm (issue 34); the arm is where the robot says it is.
        raise ApiError(409, "arm_in_view", f"{arm.what} cover {share:.0%} of the ROI in camera {cam_id}'s image "
                                           "(projected through the active hand-eye at the robot's pose): move the "
                                           "robot out of the camera's view and teach again")
    try:
        check_roi(body.roi, frame.size)
        model = await run_in_threadpool(
            lambda: teach_model(frame.pixels, body.roi, mode=body.mode, name=body.name,
                                shape_params=TeachParams(colour=colour_mode(body.mode, body.colour)),
                                refine=body.refine,
                                more_views=[(frame.pixels, r) for r in body.more_rois]))
    except NotRoundPart as exc:
        raise ApiError(422, "not_round", str(exc)) from None
    except ValueError as exc:
        raise ApiError(422, "cannot_teach", str(exc)) from None
    out: dict[str, Any] = model.to_dict()
    if preview:
        u, v = model.reference_px
        segments = model.contour(u, v, 0.0)
        out["preview"] = {"summary": model.summary(), "frame_size": list(frame.size),
                          "edges_px": [[[round(float(a), 1), round(float(b), 1)] for a, b in seg] for seg in segments]}
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
    except UnusableCalibration as exc:
        raise ApiError(409, "calibration_unusable", str(exc)) from None
    except (PickError, ModelFileError, ValidationError) as exc:
        raise ApiError(422, "cannot_pick", str(exc)) from None
    log.info("pick recipe %d: %d picks, trigger-to-answer %.1f ms", body.recipe_id, len(answer["picks"]),
             answer["latency_ms"]["total"])
    if not answer.get("reason"):  # the search's own reason first; else why no match is usable
        answer["reason"] = await run_in_threadpool(_why_nothing, services, body.recipe_id, answer)
    return answer


def _why_nothing(services: ServicesDep, recipe_id: int, answer: dict[str, Any]) -> str | None:
    """Why the answer holds no (reachable) pick, in words an operator can act on; None when it has one."""
    picks = answer.get("picks") or []
    if any(p.get("reachable") for p in picks):
        return None
    if picks:
        return (f"{len(picks)} part(s) found, none reachable: {picks[0].get('not_reachable_reason')}; check the "
                "recipe's grasp_z_mm / approach_height_mm and the robot's envelope")
    recipe = Recipe.model_validate(services.store.get_recipe(recipe_id, answer.get("recipe_version")).data)
    sp = recipe.search
    if answer.get("timed_out"):
        return (f"the search stopped at its time limit (search.timeout_s = {sp.timeout_s} s) before finding a part; "
                "raise timeout_s, narrow search.roi or the angle range")
    where = ": check that the part is in view and lit as when taught, or lower min_score"
    pose = recipe.capture_pose_ur
    now = answer.get("capture_pose")
    if pose is not None and isinstance(now, dict):
        d_mm = 1e3 * math.dist(pose[:3], [now.get("x_mm", 0.0) / 1e3, now.get("y_mm", 0.0) / 1e3,
                                          now.get("z_mm", 0.0) / 1e3])
        if d_mm > 1.0:
            where = (f"; the robot is {d_mm:.0f} mm from the recipe's capture pose: move it back there "
                     f"(capture_pose_ur {[round(x, 4) for x in pose]}) and pick again")
    return (f"no part scored at least search.min_score = {sp.min_score:g} in camera {answer.get('camera_id')}'s "
            f"frame (see {answer.get('image_url')}){where}")


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
