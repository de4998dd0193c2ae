"""Production over REST: start, watch, pause, resume and stop a run; its cycles; the next place slot.

``POST /production/start`` (engineer) answers 202 with the run id; the run owns the robot's motion
until it ends. ``POST /robots/{id}/stop`` stays the emergency path: the run ends ``stopped`` at
once and a held part stays gripped. docs/production.md is the contract.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import cv2
from fastapi import APIRouter, Path, Query
from fastapi.responses import PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Engineer, Operator, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.cell import UnknownDevice
from cellctl.mapping import NoCalibration
from cellctl.pick.frames import annotate
from cellctl.pick.recipe import PickError, Recipe
from cellctl.production.manager import GripperHolding, NoRun, ProductionManager, ProductionRunning
from cellctl.production.records import to_csv
from cellctl.store import NotFound
from cellctl.strict_types import Bool, Count

router = APIRouter(prefix="/production", tags=["production"], route_class=EdgeRoute)


class StartInput(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    recipe_id: Count = Field(ge=0, le=65535, description="the recipe to run (it needs a place section and a "
                                                       "gripper device)")
    count: Count = Field(0, ge=0, le=1_000_000, description="parts to place; 0: until the area is empty")
    robot_id: str | None = Field(None, max_length=128, description="default: the recipe's, else "
                                                                   "calibration.robot")
    camera_id: str | None = Field(None, max_length=128, description="default: the recipe's, else "
                                                                    "calibration.camera")
    overlap: Bool = Field(True, description="with a fixed camera, take and search the next picture while the "
                                            "robot places (false: after it is back, for comparison)")


class ConfirmInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: Count = Field(ge=0, le=65535, description="the recipe whose place pattern the slot is of")
    occupied: Bool = Field(description="true: a part is in the slot (it stays used); false: the slot is empty "
                                       "(the next part may go there)")


class SlotInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    recipe_id: Count = Field(ge=0, le=65535)
    next_slot: Count = Field(ge=0, le=1_000_000, description="the next free slot (0-based) of the recipe's place "
                                                          "pattern")



def _manager(services: ServicesDep) -> ProductionManager:
    return services.production


def _current(services: ServicesDep, robot_id: str | None) -> dict[str, Any]:
    try:
        return _manager(services).current(robot_id)
    except NoRun as exc:
        raise ApiError(404, "no_run", str(exc)) from None


@router.post("/start", status_code=202, responses={404: {}, 409: {}, 422: {}, 503: {}})
async def start(body: StartInput, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Start a run (engineer): 409 ``robot_busy`` / ``robot_stopped`` as for any motion, 409
    ``production_running`` when a run already owns the robot, 409 ``gripper_holding`` when the
    gripper holds something."""
    manager = _manager(services)
    try:
        run = await run_in_threadpool(manager.start, body.recipe_id, body.count, who.name, body.robot_id,
                                      body.camera_id, body.overlap)
    except NotFound:
        raise ApiError(404, "unknown_recipe", f"no recipe {body.recipe_id} (GET /recipes lists them)") from None
    except UnknownDevice as exc:
        raise ApiError(404, "unknown_device", str(exc)) from None
    except ProductionRunning as exc:
        raise ApiError(409, "production_running", str(exc)) from None
    except GripperHolding as exc:
        raise ApiError(409, "gripper_holding", str(exc)) from None
    except (PickError, NoCalibration) as exc:
        raise ApiError(422, "cannot_run", str(exc)) from None
    services.store.audit(who.name, "production.start", str(body.recipe_id),
                         {"run_id": run.status.run_id, "count": body.count, "robot_id": run.s.robot_id}, "ok")
    return {"run_id": run.status.run_id, "state": run.status.state}


@router.get("", responses={404: {}})
def current(services: ServicesDep, _: Viewer, robot_id: str | None = None,
            none_ok: Annotated[bool, Query(description="no run yet: answer 200 {\"run_id\": null, \"state\": null} "
                                                       "instead of 404 no_run (a page that polls)")] = False,
            ) -> dict[str, Any]:
    """The current or last run: state, ended_because, counters, cycle_ms, next_slot."""
    try:
        return _current(services, robot_id)
    except ApiError as exc:
        if none_ok and exc.code == "no_run":
            return {"run_id": None, "state": None, "message": exc.message}
        raise


@router.post("/pause", responses={404: {}})
def pause(services: ServicesDep, who: Operator, robot_id: str | None = None) -> dict[str, Any]:
    """Pause after the current cycle (operator)."""
    run = _run(services, robot_id)
    run.pause()
    services.store.audit(who.name, "production.pause", str(run.status.run_id), {}, "ok")
    return run.public()


@router.post("/resume", responses={404: {}, 409: {}})
def resume(services: ServicesDep, who: Operator, robot_id: str | None = None) -> dict[str, Any]:
    """Resume a paused run (operator); 409 ``robot_stopped`` while the robot is latched."""
    run = _run(services, robot_id)
    _manager(services).resume(robot_id)
    services.store.audit(who.name, "production.resume", str(run.status.run_id), {}, "ok")
    return run.public()


@router.post("/stop", responses={404: {}})
def stop(services: ServicesDep, who: Operator, robot_id: str | None = None) -> dict[str, Any]:
    """End the run after the current cycle (operator). The emergency stop is POST /robots/{id}/stop."""
    run = _run(services, robot_id)
    run.stop()
    services.store.audit(who.name, "production.stop", str(run.status.run_id), {}, "ok")
    return run.public()


@router.get("/runs/{run_id}/cycles", responses={404: {}}, response_model=None)
def cycles(run_id: Annotated[int, Path(ge=1, le=2**62)], services: ServicesDep, _: Viewer,
           format: Annotated[Literal["json", "csv"], Query(description="json (default) or csv")] = "json",
           ) -> Response | list[dict[str, Any]]:
    """The run's cycle records, oldest first (``?format=csv``: the same as CSV)."""
    store = _manager(services).store
    try:
        store.get_run(run_id)
    except NotFound as exc:
        raise ApiError(404, "unknown_run", str(exc)) from None
    records = store.cycles(run_id)
    for r in records:  # where its picture is served (404 there once a placed cycle's has left the cache)
        r["frame_url"] = (f"/production/runs/{run_id}/cycles/{r['n']}/frame.png"
                          if r.get("frame_kept") or r.get("frame_id") is not None else None)
    if format == "csv":
        return PlainTextResponse(to_csv(records), media_type="text/csv",
                                 headers={"Content-Disposition": f'attachment; filename="run-{run_id}-cycles.csv"'})
    return records


@router.get("/runs/{run_id}/cycles/{n}/frame.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, 404: {}})
def cycle_frame(run_id: Annotated[int, Path(ge=1, le=2**62)], n: Annotated[int, Path(ge=1, le=2**31)],
                services: ServicesDep, _: Viewer,
                annotated: Annotated[bool, Query(description="draw the matches (false: the pixels as grabbed)")]
                = True) -> Response:
    """The picture cycle ``n`` of the run chose from: a failed cycle's from disk (kept, within the
    cell's bounds), any other from the service's last frames while it is among them; 404
    ``unknown_frame`` when it is not kept."""
    manager = _manager(services)
    try:
        record = next((r for r in manager.store.cycles(run_id) if int(r["n"]) == n), None)
    except NotFound:
        record = None
    if record is None:
        raise ApiError(404, "unknown_cycle", f"run {run_id} has no cycle {n} (GET /production/runs/{run_id}/cycles)")
    try:
        if record.get("frame_kept"):
            frame = manager.failure_frames.load(int(record.get("run_id") or run_id), n)  # named when written
        elif record.get("frame_id") is not None:
            frame = services.frames.get(int(record["frame_id"]))
        else:
            raise KeyError(f"cycle {n} of run {run_id} took no picture")
    except KeyError as exc:
        raise ApiError(404, "unknown_frame", f"cycle {n}'s frame is not kept: {exc.args[0]}") from None
    ok, buf = cv2.imencode(".png", annotate(frame) if annotated else frame.pixels)
    if not ok:
        raise ApiError(500, "encode_failed", "the frame could not be encoded")
    return Response(buf.tobytes(), media_type="image/png", headers={"Cache-Control": "no-store"})


@router.put("/slot", responses={404: {}, 409: {}, 422: {}})
def set_slot(body: SlotInput, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Set the recipe's next free place slot (engineer); stored, it survives a restart."""
    try:
        recipe = Recipe.model_validate(services.store.get_recipe(body.recipe_id).data)
    except NotFound:
        raise ApiError(404, "unknown_recipe", f"no recipe {body.recipe_id} (GET /recipes lists them)") from None
    n = None if recipe.place is None else recipe.place.slot_count()
    if n is not None and body.next_slot > n:
        raise ApiError(422, "invalid_slot", f"recipe {body.recipe_id}'s place pattern has {n} slots (0..{n - 1}); "
                                            f"next_slot {body.next_slot} is beyond it")
    manager = _manager(services)
    running = manager.running(body.recipe_id)
    if running:
        raise ApiError(409, "production_running", f"production run {running[0].status.run_id} places recipe "
                                                  f"{body.recipe_id}'s parts now; stop it before setting the slot")
    manager.store.set_next_slot(body.recipe_id, body.next_slot, who.name)
    services.store.audit(who.name, "production.slot", str(body.recipe_id), {"next_slot": body.next_slot}, "ok")
    return {"recipe_id": body.recipe_id, "next_slot": manager.store.next_slot(body.recipe_id)}


@router.post("/slots/{slot}/confirm", responses={404: {}, 422: {}})
def confirm_slot(slot: Annotated[int, Path(ge=0, le=1_000_000)], body: ConfirmInput, services: ServicesDep,
                 who: Engineer) -> dict[str, Any]:
    """Say what is in a slot in doubt (engineer), after looking: ``occupied`` true keeps it used,
    false frees it (the counter goes back to it when it is just past it). 404 ``slot_not_in_doubt``
    when the slot is not in doubt. Audited (``production.slot_confirm``)."""
    try:
        return _manager(services).store.confirm_slot(body.recipe_id, slot, body.occupied, who.name)
    except NotFound as exc:
        raise ApiError(404, "slot_not_in_doubt", str(exc)) from None


@router.post("/gripper/open", responses={404: {}, 409: {}})
def open_gripper(services: ServicesDep, who: Engineer,
                 recipe_id: Annotated[int, Query(ge=0, le=65535)]) -> dict[str, Any]:
    """Open the recipe's gripper by hand (engineer), e.g. after a Stop left a part gripped."""
    try:
        out = _manager(services).open_gripper(recipe_id)
    except NotFound:
        raise ApiError(404, "unknown_recipe", f"no recipe {recipe_id}") from None
    except ProductionRunning as exc:
        raise ApiError(409, "production_running", str(exc)) from None
    except PickError as exc:
        raise ApiError(422, "cannot_run", str(exc)) from None
    services.store.audit(who.name, "production.gripper_open", str(recipe_id), out, "ok")
    return out


def _run(services: ServicesDep, robot_id: str | None) -> Any:
    try:
        return _manager(services).run(robot_id)
    except NoRun as exc:
        raise ApiError(404, "no_run", str(exc)) from None
