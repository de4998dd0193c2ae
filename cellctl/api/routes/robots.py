"""Robots: list and state (pose in UR form with units in the names, and the 4x4)."""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field, field_validator

from calibration import geometry as g
from cellctl.api.body import EdgeRoute
from cellctl.api.deps import CellDep, Engineer, Operator, Viewer, device_call, slot_or_404
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.api.pools import run_blocking
from cellctl.motion import audited_move
from cellctl.numbers import pose_ur_problem, transform_problem
from cellctl.robot_state import state_to_json
from cellctl.store.errors import StoreUnavailable
from cellctl.strict_types import Num
from drivers.base import DeviceUnavailable, MotionSession, Robot, RobotBase, RobotState

log = logging.getLogger(__name__)
router = APIRouter(prefix="/robots", tags=["robots"], route_class=EdgeRoute)

MAX_STATE_AGE_S = 1.0
MOVE_TIMEOUT_S = 120.0
LATCH_STORE_WAIT_S = 5.0


class PoseUR(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x_m: float
    y_m: float
    z_m: float
    rx_rad: float
    ry_rad: float
    rz_rad: float


Metres = Annotated[Num, Field(ge=-100.0, le=100.0)]
"""A strict coordinate in metres (no bool, no string; beyond 100 m is no work cell)."""
Radians = Annotated[Num, Field(ge=-10.0, le=10.0)]
"""A strict rotation-vector component in radians (the vector's norm is checked to be one turn at most)."""


class PoseURInput(BaseModel):
    """A UR pose in a request: metres and a rotation vector in radians, each a JSON number."""

    model_config = ConfigDict(extra="forbid")
    x_m: Metres
    y_m: Metres
    z_m: Metres
    rx_rad: Radians
    ry_rad: Radians
    rz_rad: Radians


class RobotStatePublic(BaseModel):
    robot_id: str
    T_base_tool: list[list[float]]
    pose_ur: PoseUR
    joints_rad: list[float]
    timestamp_s: float
    age_s: float
    moving: bool
    mode: str
    latched: bool = False
    """True while a Stop latches the robot (no motion until an engineer resumes)."""


def _slot(cell: CellDep, robot_id: str) -> Any:
    return slot_or_404(cell.robots, "robot", robot_id)


@router.get("")
def list_robots(cell: CellDep, services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    """Each robot's status, motion owner and latch, and its named poses (``poses``: name → UR pose, m/rad)."""
    robots = services.config.robots
    return [{**slot.status(), "motion": slot.device.motion.status(),
             "poses": {k: list(v) for k, v in (robots[rid].poses if rid in robots else {}).items()}}
            for rid, slot in cell.robots.items()]


@router.get("/{robot_id}/state", response_model=RobotStatePublic, responses={503: {}})
async def robot_state(robot_id: str, cell: CellDep, _: Viewer) -> dict[str, Any]:
    slot = _slot(cell, robot_id)

    def read(robot: Robot) -> RobotState:
        return robot.state()

    state: RobotState = await device_call(slot, read)
    out = state_to_json(robot_id, state)
    if out["age_s"] > MAX_STATE_AGE_S:
        # A stale pose is never served as current.
        raise DeviceUnavailable(f"robot {robot_id}: newest state is {out['age_s']:.2f} s old "
                                f"(limit {MAX_STATE_AGE_S} s)")
    out["latched"] = slot.device.motion.latched
    return out


class MoveInput(BaseModel):
    """A linear move of the tool to ``T_base_tool`` (4x4, m), to a UR pose (m, rad) or to a pose named
    in the config (``robots.<id>.poses``); speed in m/s. Give exactly one of the three."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    T_base_tool: list[Annotated[list[Annotated[Num, Field(ge=-1e3, le=1e3)]], Field(max_length=4)]] | None = Field(
        None, max_length=4)
    pose_ur: PoseURInput | None = None
    named_pose: str | None = Field(None, max_length=40, description="a pose named in the config's robots.<id>.poses "
                                                                    "(GET /robots lists them), e.g. home")
    speed_m_s: Num = Field(0.05, gt=0, le=5.0)

    @field_validator("pose_ur")
    @classmethod
    def _pose_magnitudes(cls, v: PoseURInput | None) -> PoseURInput | None:
        problem = None if v is None else pose_ur_problem(
            [v.x_m, v.y_m, v.z_m, v.rx_rad, v.ry_rad, v.rz_rad], "pose_ur")
        if problem:
            raise ValueError(problem)
        return v

    @field_validator("T_base_tool")
    @classmethod
    def _matrix_magnitudes(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        problem = None if v is None else transform_problem(v, "T_base_tool")
        if problem:
            raise ValueError(problem)
        return v


@router.post("/{robot_id}/move", response_model=RobotStatePublic, responses={409: {}, 422: {}, 503: {}})
async def move(robot_id: str, body: MoveInput, cell: CellDep, services: ServicesDep, who: Engineer
               ) -> dict[str, Any]:
    """Move the tool (engineer). 409 ``robot_busy`` while another motion owns the robot, 409
    ``robot_stopped`` while it is latched by a Stop, or when a Stop halted this move."""
    slot = _slot(cell, robot_id)
    given = [k for k in ("T_base_tool", "pose_ur", "named_pose") if getattr(body, k) is not None]
    if len(given) != 1:
        raise ApiError(422, "invalid_request", "give exactly one of T_base_tool (4x4, m), pose_ur (m, rad) or "
                                               "named_pose (a name from the config's robots.<id>.poses)"
                                               + (f"; got {' and '.join(given)}" if given else ""))
    try:
        if body.named_pose is not None:
            T = g.ur_pose_to_transform(list(_named_pose(services, robot_id, body.named_pose)))
        elif body.pose_ur is not None:
            p = body.pose_ur
            T = g.ur_pose_to_transform([p.x_m, p.y_m, p.z_m, p.rx_rad, p.ry_rad, p.rz_rad])
        elif body.T_base_tool is not None:
            T = g.as_transform(body.T_base_tool, "T_base_tool")
    except g.PoseError as exc:
        raise ApiError(422, "invalid_pose", str(exc)) from None

    what = f"POST /robots/{robot_id}/move" + (f" named_pose {body.named_pose}" if body.named_pose is not None else "")

    def go(robot: RobotBase) -> RobotState:
        audited_move(services.store, who.name, robot, T, body.speed_m_s, what)
        return robot.state()

    deadline_s = await device_call(slot, lambda robot: robot.move_deadline_s(T, body.speed_m_s))
    # The robot's own deadline stops a late move; the request waits a little longer for that answer.
    state: RobotState = await device_call(slot, go, timeout_s=min(deadline_s, MOVE_TIMEOUT_S) + 5.0)
    return state_to_json(robot_id, state)


def _named_pose(services: ServicesDep, robot_id: str, name: str) -> tuple[float, ...]:
    robot = services.config.robots.get(robot_id)
    poses = robot.poses if robot is not None else {}
    if name not in poses:
        known = ", ".join(sorted(poses)) or "none (add them under robots.<id>.poses in cell.yaml)"
        raise ApiError(422, "unknown_pose", f"robot {robot_id} has no pose named {name!r}; named poses: {known}")
    return tuple(poses[name])


@router.post("/{robot_id}/stop")
async def stop(robot_id: str, cell: CellDep, services: ServicesDep, who: Operator) -> dict[str, Any]:
    """Halt the robot now (operator), abort the sequence that moves it, and latch it stopped.

    The latch is set even when the robot cannot be reached (then the answer is 503): nothing moves
    it again until an engineer calls ``resume``.
    """
    slot = _slot(cell, robot_id)
    robot: RobotBase = slot.device
    aborted = robot.motion.latch(who.name, "Stop")
    try:
        await device_call(slot, lambda r: r.halt())
    except Exception as exc:
        await _latch_stored(services)
        await _audit_stop(services, who.name, robot_id, aborted, f"latched; halting failed: {exc}")
        raise  # the device's error, never one of the store's
    # The latch's own write first: an audit entry written meanwhile would wait for the store's lock
    # (SQLite backs off in steps of milliseconds: ~30 ms added to a Stop's answer).
    stored = await _latch_stored(services)
    audited = await _audit_stop(services, who.name, robot_id, aborted, "ok")
    return {"robot_id": robot_id, "stopped": True, "aborted": _what(aborted), **robot.motion.status(),
            "latch_stored": stored, "audit_stored": audited}


async def _audit_stop(services: ServicesDep, who: str, robot_id: str, aborted: Any, result: str) -> bool:
    """Audit a Stop; False when the store cannot take it. The robot has stopped either way: a store
    that is down must not turn the Stop's answer into an error (the log keeps the record)."""
    try:
        # The store is written in the safety pool (cellctl.api.pools), never on the event loop.
        await run_blocking(services.store.audit, who, "robot.stop", robot_id, {"aborted": _what(aborted)}, result)
        return True
    except StoreUnavailable as exc:
        log.error("robot %s stopped by %s (%s); its audit entry was not stored: %s", robot_id, who, result, exc)
        return False


@router.post("/{robot_id}/resume")
async def resume(robot_id: str, cell: CellDep, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Clear the Stop latch (engineer): the robot may be moved again."""
    robot: Robot = _slot(cell, robot_id).device

    def clear() -> tuple[bool, bool]:
        was = robot.resume(who.name)
        # As for Stop: the latch's write first, then the audit entry (no wait for the store's lock).
        stored = services.latches is not None and services.latches.wait_stored_blocking(LATCH_STORE_WAIT_S)
        services.store.audit(who.name, "robot.resume", robot_id, {"was_latched": was}, "ok")
        return was, stored

    was, stored = await run_blocking(clear)  # the safety pool: a flood that fills the default pool cannot delay it
    return {"robot_id": robot_id, "resumed": was, **robot.motion.status(), "latch_stored": stored}


async def _latch_stored(services: ServicesDep) -> bool:
    """True once the latch's change is in the store (it then outlives a crash); False after a few seconds."""
    return services.latches is not None and await services.latches.wait_stored(LATCH_STORE_WAIT_S)


@router.get("/{robot_id}/motion")
async def motion_status(robot_id: str, cell: CellDep, _: Viewer) -> dict[str, Any]:
    """Whether the robot is latched by a Stop, and who owns its motion now."""
    robot: Robot = _slot(cell, robot_id).device
    return {"robot_id": robot_id, **robot.motion.status()}


def _what(session: MotionSession | None) -> str | None:
    return None if session is None else f"{session.what} (by {session.who})"
