"""``handeye-capture``: planned, reachable robot stations around the plate, then hand-eye.

Eye-in-hand: the tool pivots about the plate's centre with tilts in spread directions and spins
about the view axis (rotation axes diverse, pairs well conditioned). Degeneracy is checked as
stations come in (the spread of the relative rotation axes); the solver's own checks run at the
end. Uses the active camera calibration of the camera; stores, does not activate.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration import geometry as g
from calibration.handeye import calibrate_handeye
from cellctl.jobs import JobContext
from cellctl.mapping import active_camera
from cellctl.routines.common import (
    Capture,
    RoutineError,
    capture,
    detection_inputs,
    devices,
    move,
    pivot_point,
    plan_pivot_stations,
    reachable,
    routine_target,
    stop_robot_on_end,
    target_pose,
)
from cellctl.services import Services


class Params(BaseModel):
    """Parameters of ``handeye-capture`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="HandeyeCaptureParams")

    camera_id: str | None = Field(None, description="camera to calibrate (default: the config's calibration.camera)")
    robot_id: str | None = Field(None, description="robot to use (default: the config's calibration.robot)")
    target: str | None = Field(None, description="name of a target in the config's targets "
                                                 "(default: calibration.target)")
    setup: Literal["eye-in-hand", "eye-to-hand"] | None = Field(
        None, description="where the camera is; default: the config's calibration.setup")
    stations: int = Field(12, ge=4, le=40, description="number of robot stations, including the start pose")
    max_tilt_deg: float = Field(25.0, ge=5, le=45, description="largest tilt about the plate's centre, degrees "
                                                               "(the checks ask for 15-30)")
    max_spin_deg: float = Field(40.0, ge=0, le=90, description="largest spin about the view axis, degrees")
    speed_m_s: float | None = Field(None, ge=0.001, le=2.0, description="tool speed, m/s, 0.001-2 "
                                                                    "(default: calibration.speed_m_s)")
    note: str = Field("", max_length=500, description="note stored with the calibration")


def rotation_axis_spread_deg(poses: list[np.ndarray]) -> float:
    """Largest angle between the rotation axes of the relative motions from the first pose."""
    axes = []
    for T in poses[1:]:
        rv = g.matrix_to_rotvec(poses[0][:3, :3].T @ T[:3, :3])
        if np.linalg.norm(rv) > np.radians(2):
            axes.append(rv / np.linalg.norm(rv))
    best = 0.0
    for i in range(len(axes)):
        for j in range(i + 1, len(axes)):
            best = max(best, float(np.degrees(np.arccos(np.clip(abs(axes[i] @ axes[j]), -1, 1)))))
    return best


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    defaults = services.config.calibration
    camera_id = p.camera_id or defaults.camera
    robot_id = p.robot_id or defaults.robot
    setup = p.setup or defaults.setup
    if setup != "eye-in-hand":
        raise RoutineError("handeye-capture plans stations for eye-in-hand cells; for eye-to-hand, capture "
                           "the stations yourself and run `cellctl calib handeye --setup eye-to-hand`")
    tname, target = routine_target(services, p.target)
    found = active_camera(services, camera_id)
    if found is None:
        raise RoutineError(f"camera {camera_id} has no active calibration; run intrinsics-capture and "
                           "activate its result first")
    active, camera = found
    cam, robot = devices(services, camera_id, robot_id)
    if robot is None:
        raise RoutineError(f"routine needs robot {robot_id!r}; name a configured robot (robot_id)")
    stop_robot_on_end(ctx, robot)
    first = capture(cam, robot, target, "station01")
    if not first.detection.found:
        raise RoutineError(f"the plate is not seen from the start pose ({first.detection.reason}); move the "
                           "robot so the whole plate is in view, then start again")
    if first.T_base_tool is None:
        raise RoutineError("the start view has no robot pose; the robot must report its pose")
    T_cam_target = target_pose(camera, target, first.detection)
    plan = plan_pivot_stations(first.T_base_tool, pivot_point(first.T_base_tool, T_cam_target, target),
                               p.stations, p.max_tilt_deg, p.max_spin_deg, None)
    stations, unreachable = reachable(robot, plan[1:])
    caps: list[Capture] = [first]
    speed = p.speed_m_s or defaults.speed_m_s
    for k, T in enumerate(stations):
        ctx.check_cancelled()
        move(services, ctx, robot, T, speed, f"handeye-capture station {k + 2}")
        c = capture(cam, robot, target, f"station{k + 2:02d}")
        if c.detection.found:
            caps.append(c)
        spread = rotation_axis_spread_deg([c.T_base_tool for c in caps if c.T_base_tool is not None])
        ctx.report((k + 2) / (len(stations) + 3),
                   f"station {k + 2}/{len(stations) + 1}: " + ("ok" if c.detection.found else
                                                                f"rejected ({c.detection.reason})"),
                   rotation_axis_spread_deg=round(spread, 1))
    move(services, ctx, robot, first.T_base_tool, speed, "handeye-capture: back to start")
    ctx.check_cancelled()
    ctx.report(0.95, f"solving hand-eye from {len(caps)} stations")
    poses = [c.T_base_tool for c in caps if c.T_base_tool is not None]
    result = calibrate_handeye(setup, poses, [c.detection for c in caps], camera, target)
    he = result.to_json()
    he["camera_calibration_id"] = active.id
    he["target"] = tname
    record = services.store.save_calibration(
        "handeye", camera_id, robot_id, he,
        {"target": services.config.targets[tname], "camera": active.result, "stations": detection_inputs(caps)},
        creator=ctx.started_by, note=p.note or f"handeye-capture, {len(caps)} stations")
    name = "T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"
    return {"calibration_id": record.id, "version": record.version, "kind": "handeye", "setup": setup,
            name: he[name], "rms_px": he["rms_px"], "uncertainty": {k: he["uncertainty"][k] for k in
                                                                   ("rot_deg", "trans_mm")},
            "stations_used": len(caps), "stations_unreachable": unreachable,
            "verdict": he.get("verdict"), "activated": False}
