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
    capture,
    detection_inputs,
    devices,
    move,
    routine_target,
    stop_robot_on_end,
)
from cellctl.routines.planned_capture import PlannedCapture
from cellctl.services import Services


class Params(BaseModel):
    """Parameters of ``intrinsics-capture`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="IntrinsicsCaptureParams")

    camera_id: str | None = Field(None, description="camera to calibrate (default: the config's calibration.camera)")
    robot_id: str | None = Field(None, description="robot to use (default: the config's calibration.robot)")
    target: str | None = Field(None, description="name of a target in the config's targets "
                                                 "(default: calibration.target)")
    model: Literal["opencv5", "opencv8", "division"] | None = Field(
        None, description="lens model: opencv5 (k1,k2,p1,p2,k3), opencv8 (rational) or division (one kappa); "
                          "default: the config's calibration.model")
    mode: Literal["robot", "operator"] = Field(
        "robot", description="robot: the robot shows the plate from planned views (engineer role); "
                             "operator: the operator presents the plate by hand and records each view")
    views: int = Field(16, ge=4, le=60, description="good views to collect before the first verdict, "
                                                    "including the start pose")
    max_views: int = Field(32, ge=4, le=120, description="robot mode: most views to try (rejected and "
                                                         "unreachable ones count); the routine adds views "
                                                         "until the verdict is ok or this budget is spent")
    max_tilt_deg: float = Field(32.0, ge=5, le=60, description="largest tilt of the view direction, degrees")
    min_point_fraction: float = Field(0.8, gt=0, le=1, description="a view counts when at least this fraction "
                                                                   "of the target's points is detected")
    speed_m_s: float | None = Field(None, ge=0.001, le=2.0, description="tool speed, m/s, 0.001-2 "
                                                                    "(default: calibration.speed_m_s)")
    step_timeout_s: float = Field(600.0, gt=0, le=86400, description="operator mode: a view not recorded within "
                                                                     "this many seconds cancels the job")
    note: str = Field("", max_length=500, description="note stored with the calibration")


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
                                           "then record"}, timeout_s=p.step_timeout_s)
            c = capture(cam, None, target, f"view{k + 1:02d}", ctx)
            if good(c):
                caps.append(c)
            else:
                skipped += 1
            ctx.report((k + 1) / (p.views + 1), f"view {k + 1}/{p.views}: "
                       + ("ok" if good(c) else f"rejected ({c.detection.reason or 'too few points'})"))
    else:
        first = capture(cam, robot, target, "view01", ctx)
        if not good(first) or first.T_base_tool is None:
            raise RoutineError(f"the plate is not seen from the start pose ({first.detection.reason}); "
                               "move the robot so the whole plate is in view, then start again")
        ctx.report(0.02, "view 1: ok (start pose)")
        caps.append(first)
        planned = PlannedCapture(services, ctx, robot, cam, target, p, good, first, caps)
        result, skipped = planned.run()
        move(services, ctx, robot, first.T_base_tool, planned.speed, "intrinsics-capture: back to start")
    if robot is None:
        ctx.check_cancelled()
        ctx.report(0.95, f"calibrating {model} from {len(caps)} views")
        result = calibrate([c.detection for c in caps], target, model)
    ctx.check_cancelled()
    cam_json = result.to_json()
    cam_json["target"] = tname
    record = services.store.save_calibration(
        "camera", camera_id, None, cam_json,
        {"target": services.config.targets[tname], "views": detection_inputs(caps),
         "capture": {"views_tried": len(caps) + skipped, "views_rejected": skipped}},  # the report's counts
        creator=ctx.started_by, note=p.note or f"intrinsics-capture, {len(caps)} views")
    return {"calibration_id": record.id, "version": record.version, "kind": "camera", "camera_id": camera_id,
            "views_used": len(caps), "views_rejected": skipped, "rms_px": cam_json.get("rms_px"),
            "uncertainty": cam_json.get("uncertainty"), "verdict": cam_json.get("verdict"),
            "K": cam_json.get("K"), "dist": cam_json.get("dist"), "activated": False}
