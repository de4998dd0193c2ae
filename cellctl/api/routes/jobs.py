"""Routines as jobs: ``POST /routines/{name}`` starts one; ``/jobs`` reads, follows (SSE), cancels."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Body, Request
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Operator, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.jobs import JobInputError
from cellctl.routines import ENGINEER_ONLY, MOVES_ROBOT, NEEDS_CONVEYOR, ROUTINE_MODULES, routine
from cellctl.routines.start import StartRefused
from cellctl.routines.start import start_routine as start_job
from cellctl.strict_types import Num

router = APIRouter(tags=["jobs"], route_class=EdgeRoute)


class JobPublic(BaseModel):
    id: str
    name: str
    state: str
    progress: float
    message: str
    result: dict[str, Any] | None
    error: str | None
    started_by: str
    params: dict[str, Any]
    created_s: float
    finished_s: float | None
    waiting_for: dict[str, Any] | None
    events: int
    verdict_ok: bool | None = None
    """A succeeded job's verdict (a calibration's verdict.ok, verify's passed); false: NOT OK (the state stays
    succeeded: the result is there to be looked at); null: running, ended otherwise, or no verdict."""


class RecordInput(BaseModel):
    """Operator input for a waiting routine (jog-to-mark: the tool is at the mark)."""

    model_config = ConfigDict(extra="forbid")
    x_mm: Num | None = Field(None, ge=-1e5, le=1e5,
                               description="robot x of the mark, mm (default: read from the robot)")
    y_mm: Num | None = Field(None, ge=-1e5, le=1e5,
                               description="robot y of the mark, mm (default: read from the robot)")


class RoutinePublic(BaseModel):
    name: str
    description: str
    moves_robot: bool
    role: str
    """The least role that may start it (operator mode of intrinsics-capture needs only operator)."""
    params_schema: dict[str, Any]
    """JSON schema of the routine's parameters (units in names and descriptions, defaults)."""


def _describe(name: str) -> dict[str, Any]:
    module = routine(name)
    doc = (module.__doc__ or "").strip().split("\n\n")[0].replace("``", "")
    return {"name": name, "description": " ".join(doc.split()), "moves_robot": name in MOVES_ROBOT,
            "role": "engineer" if name in MOVES_ROBOT | ENGINEER_ONLY else "operator",
            "params_schema": module.Params.model_json_schema()}


@router.get("/routines", response_model=list[RoutinePublic])
def list_routines(services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    """Each routine the cell can run with the JSON schema of its parameters (``POST /routines/{name}`` takes
    them); ``conveyor-calibrate`` is listed when the config names a conveyor."""
    return [_describe(n) for n in sorted(ROUTINE_MODULES)
            if n not in NEEDS_CONVEYOR or services.config.conveyors]


def _start(name: str, services: ServicesDep, who: Operator, params: dict[str, Any] | None) -> dict[str, Any]:
    """The routine started by the service's one start (``cellctl.routines.start``), its refusals as HTTP."""
    try:
        job = start_job(services, name, params, who)
    except StartRefused as exc:
        raise ApiError(exc.status, exc.code, str(exc)) from None
    public: dict[str, Any] = job.public()
    return public


def _add_routine_route(name: str) -> None:
    """``POST /routines/<name>``, its body documented in OpenAPI by the routine's ``Params`` model.

    The body is validated in the handler (not by FastAPI), so the role check comes before the
    parameter check and errors keep the ``invalid_params`` code.
    """
    info = _describe(name)

    async def start(request: Request, services: ServicesDep, who: Operator) -> dict[str, Any]:
        raw = await request.body()
        try:
            params = await request.json() if raw.strip() else None  # the edge's parse (cellctl.api.body)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ApiError(422, "invalid_params", f"routine {name}: the body is not JSON ({exc})") from None
        return await run_in_threadpool(_start, name, services, who, params)

    router.add_api_route(
        f"/routines/{name}", start, methods=["POST"], status_code=202, response_model=JobPublic,
        name=f"start_{name.replace('-', '_')}", summary=f"Start {name}",
        description=f"{info['description']} Needs the {info['role']} role.",
        openapi_extra={"requestBody": {"required": False, "content": {
            "application/json": {"schema": info["params_schema"]}}}})


for _name in sorted(ROUTINE_MODULES):
    _add_routine_route(_name)


@router.post("/routines/{name}", status_code=202, response_model=JobPublic, include_in_schema=False)
def start_routine(name: str, services: ServicesDep, who: Operator,
                  params: dict[str, Any] | None = Body(None)) -> dict[str, Any]:  # noqa: B008
    return _start(name, services, who, params)


@router.get("/jobs", response_model=list[JobPublic])
def list_jobs(services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    return [j.public() for j in services.jobs.list()]


def _job(services: ServicesDep, job_id: str) -> Any:
    try:
        return services.jobs.get(job_id)
    except KeyError as exc:
        raise ApiError(404, "unknown_job", str(exc.args[0])) from None


@router.get("/jobs/{job_id}", response_model=JobPublic)
def get_job(job_id: str, services: ServicesDep, _: Viewer) -> dict[str, Any]:
    public: dict[str, Any] = _job(services, job_id).public()
    return public


@router.delete("/jobs/{job_id}", response_model=JobPublic)
def cancel_job(job_id: str, services: ServicesDep, who: Operator) -> dict[str, Any]:
    job = _job(services, job_id)
    services.jobs.cancel(job_id)
    services.store.audit(who.name, "routine.cancel", job.name, {"job_id": job_id}, "requested")
    public: dict[str, Any] = job.public()
    return public


@router.post("/jobs/{job_id}/record", response_model=JobPublic)
def record_input(job_id: str, services: ServicesDep, who: Operator,
                 body: RecordInput | None = Body(None)) -> dict[str, Any]:  # noqa: B008
    _job(services, job_id)
    try:
        job = services.jobs.give_input(job_id, {**(body.model_dump(exclude_none=True) if body else {}),
                                                "who": who.name})
    except JobInputError as exc:
        raise ApiError(409, "not_waiting", str(exc)) from None
    public: dict[str, Any] = job.public()
    return public


@router.get("/jobs/{job_id}/events", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, services: ServicesDep, _: Viewer) -> StreamingResponse:
    job = _job(services, job_id)

    async def stream() -> AsyncIterator[str]:
        seq = -1
        while True:
            events = await run_in_threadpool(job.events_after, seq, 1.0)
            for ev in events:
                seq = ev.seq
                yield f"id: {ev.seq}\nevent: {ev.kind}\ndata: {json.dumps(ev.data)}\n\n"
            if job.closed and seq >= len(job.events) - 1:  # the end state was sent: the stream is whole
                return
            if await request.is_disconnected():
                return
            if not events:
                yield ": keep-alive\n\n"
            await asyncio.sleep(0)

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-store"})
