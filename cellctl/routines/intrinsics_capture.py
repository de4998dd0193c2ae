"""``intrinsics-capture``: the robot shows the plate to the camera from planned views, then calibrates.

Each shot is checked before it counts (target found with at least ``min_point_fraction`` of its
points). With ``mode: operator`` the routine instead waits before each shot for the operator to
present the plate and press record (``POST /jobs/{id}/record``). The new calibration is stored,
not activated.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from calibration.intrinsics import calibrate
from cellctl.jobs import JobContext
from cellctl.routines.common import (
    Capture,
    RoutineError,
    approximate_camera,
    capture,
    corner_shifts_m,
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
    model_config = ConfigDict(extra="forbid")

    camera_id: str | None = None
    robot_id: str | None = None
    target: str | None = None
    model: Literal["opencv5", "opencv8", "division"] | None = None
    mode: Literal["robot", "operator"] = "robot"
    views: int = Field(16, ge=4, le=60)
    max_tilt_deg: float = Field(32.0, ge=5, le=60)
    min_point_fraction: float = Field(0.8, gt=0, le=1)
    speed_m_s: float | None = Field(None, gt=0)
    note: str = ""


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    defaults = services.config.calibration
    camera_id = p.camera_id or defaults.camera
    robot_id = None if p.mode == "operator" else (p.robot_id or defaults.robot)
    model = p.model or defaults.model
    tname, target = routine_target(services, p.target)
    n_points = len(target.points().ids)
    cam, robot = devices(services, camera_id, robot_id)
    stop_robot_on_end(ctx, robot)

    def good(c: Capture) -> bool:
        return c.detection.found and len(c.detection.ids) >= p.min_point_fraction * n_points

    caps: list[Capture] = []
    skipped = 0
    if robot is None:
        for k in range(p.views):
            ctx.wait_input({"step": k + 1, "of": p.views,
                            "instruction": "present the plate in a new pose (tilt it, move it to image corners), "
                                           "then record"})
            c = capture(cam, None, target, f"view{k + 1:02d}")
            if good(c):
                caps.append(c)
            else:
                skipped += 1
            ctx.report((k + 1) / (p.views + 1), f"view {k + 1}/{p.views}: "
                       + ("ok" if good(c) else f"rejected ({c.detection.reason or 'too few points'})"))
    else:
        first = capture(cam, robot, target, "view01")
        if not good(first):
            raise RoutineError(f"the plate is not seen from the start pose ({first.detection.reason}); "
                               "move the robot so the whole plate is in view, then start again")
        assert first.T_base_tool is not None
        ctx.report(0.02, "view 1: ok (start pose)")
        w, h = first.frame.size
        approx = approximate_camera(w, h)
        T_cam_target = target_pose(approx, target, first.detection)
        centre = target.points().xyz_m.mean(axis=0)
        distance = float((T_cam_target[:3, :3] @ centre + T_cam_target[:3, 3])[2])
        plan = plan_pivot_stations(first.T_base_tool, pivot_point(first.T_base_tool, T_cam_target, target),
                                   p.views, p.max_tilt_deg, 25.0,
                                   corner_shifts_m(approx, distance, target, first.detection))
        stations, unreachable = reachable(robot, plan[1:])
        caps.append(first)
        speed = p.speed_m_s or defaults.speed_m_s
        for k, T in enumerate(stations):
            ctx.check_cancelled()
            move(services, ctx, robot, T, speed, f"intrinsics-capture view {k + 2}")
            c = capture(cam, robot, target, f"view{k + 2:02d}")
            if good(c):
                caps.append(c)
            else:
                skipped += 1
            ctx.report((k + 2) / (len(stations) + 2), f"view {k + 2}/{len(stations) + 1}: "
                       + ("ok" if good(c) else f"rejected ({c.detection.reason or 'too few points'})"))
        move(services, ctx, robot, first.T_base_tool, speed, "intrinsics-capture: back to start")
        skipped += unreachable
    ctx.check_cancelled()
    ctx.report(0.95, f"calibrating {model} from {len(caps)} views")
    result = calibrate([c.detection for c in caps], target, model)
    cam_json = result.to_json()
    cam_json["target"] = tname
    record = services.store.save_calibration(
        "camera", camera_id, None, cam_json,
        {"target": services.config.targets[tname], "views": detection_inputs(caps)},
        creator=ctx.started_by, note=p.note or f"intrinsics-capture, {len(caps)} views")
    return {"calibration_id": record.id, "version": record.version, "kind": "camera", "camera_id": camera_id,
            "views_used": len(caps), "views_rejected": skipped, "rms_px": cam_json.get("rms_px"),
            "uncertainty": cam_json.get("uncertainty"), "verdict": cam_json.get("verdict"),
            "K": cam_json.get("K"), "dist": cam_json.get("dist"), "activated": False}
