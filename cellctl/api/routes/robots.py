"""Robots: list and state (pose in UR form with units in the names, and the 4x4)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel

from cellctl.api.deps import CellDep, Viewer, device_call
from cellctl.api.errors import ApiError
from cellctl.robot_state import state_to_json
from drivers.base import DeviceUnavailable, RobotBase, RobotState

router = APIRouter(prefix="/robots", tags=["robots"])

MAX_STATE_AGE_S = 1.0


class RobotStatePublic(BaseModel):
    robot_id: str
    T_base_tool: list[list[float]]
    pose_ur: dict[str, float]
    joints_rad: list[float]
    timestamp_s: float
    age_s: float
    moving: bool
    mode: str


def _slot(cell: CellDep, robot_id: str) -> Any:
    if robot_id not in cell.robots:
        raise ApiError(404, "unknown_robot", f"no robot {robot_id!r}; configured: {sorted(cell.robots)}")
    return cell.robots[robot_id]


@router.get("")
def list_robots(cell: CellDep, _: Viewer) -> list[dict[str, Any]]:
    return [slot.status() for slot in cell.robots.values()]


@router.get("/{robot_id}/state", response_model=RobotStatePublic, responses={503: {}})
async def robot_state(robot_id: str, cell: CellDep, _: Viewer) -> dict[str, Any]:
    slot = _slot(cell, robot_id)

    def read(robot: RobotBase) -> RobotState:
        return robot.state()

    state: RobotState = await device_call(slot, read)
    out = state_to_json(robot_id, state)
    if out["age_s"] > MAX_STATE_AGE_S:
        # A stale pose is never served as current.
        raise DeviceUnavailable(f"robot {robot_id}: newest state is {out['age_s']:.2f} s old "
                                f"(limit {MAX_STATE_AGE_S} s)")
    return out
