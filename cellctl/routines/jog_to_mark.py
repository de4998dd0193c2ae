"""``jog-to-mark``: the N-point (jog-to-mark) calibration — the camera sees the marks, the operator jogs the
tool tip to each mark and records; the image→robot map is fitted and its error reported.

Flow: one shot of the plate from the current (capture) pose; the routine picks ``marks`` marks
spread over the plate (a 3x3 pattern by default) and, for each, waits for
``POST /jobs/{id}/record`` (the robot position is read then, or ``x_mm, y_mm`` given in the
body). Then it fits the map (model by leave-one-out unless given), stores it (not activated)
with the capture pose, and reports the residuals and its verdict (``calibration.npoint.verdict``).

With ``tool_centre`` (a fixed camera that sees a feature of the gripper), the routine then turns
the tool about z at one recorded mark and fits the tool centre (``cellctl.routines.tool_turn``):
that step moves the robot (engineer role) under the motion owner; otherwise the robot is never
moved by this routine.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from calibration import geometry as g
from calibration.handeye import MIN_ANGLES, MIN_ARC_DEG
from calibration.npoint import assess_npoint, fit_npoint
from calibration.targets import Target
from cellctl.jobs import JobContext
from cellctl.mapping import active_camera
from cellctl.routines.common import RoutineError, capture, devices, robot_still, routine_target
from cellctl.routines.tool_turn import TurnPlan, run_turn
from cellctl.services import Services
from drivers.base import RobotBusy, RobotStopped


class Params(BaseModel):
    """Parameters of ``jog-to-mark`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="JogToMarkParams")

    camera_id: str | None = Field(None, description="camera to calibrate (default: the config's calibration.camera)")
    robot_id: str | None = Field(None, description="robot to use (default: the config's calibration.robot)")
    target: str | None = Field(None, description="name of a target in the config's targets "
                                                 "(default: calibration.target)")
    marks: int = Field(9, ge=4, le=49, description="number of marks to jog to, spread over the plate")
    model: Literal["affine", "similarity", "homography"] | None = Field(
        None, description="image-to-robot map; default: chosen by leave-one-out error")
    undistort: bool = Field(True, description="remove lens distortion first when the camera has an active "
                                              "calibration")
    step_timeout_s: float = Field(600.0, gt=0, le=86400, description="a mark not recorded within this many "
                                                                     "seconds cancels the job (abandoned wizard)")
    note: str = Field("", max_length=500, description="note stored with the calibration")
    tool_centre: bool = Field(False, description="after the marks, turn the tool about z at one mark and fit the "
                                                 "tool centre (fixed camera that sees a feature of the gripper; "
                                                 "moves the robot: engineer role)")
    tcp_angles_deg: list[float] = Field(
        [-90.0, -60.0, -30.0, 0.0, 30.0, 60.0, 90.0], min_length=MIN_ANGLES, max_length=36,
        description=f"tool angles about base z for the tool centre, degrees from the mark's recorded "
                    f"orientation (at least {MIN_ANGLES}, spanning at least {MIN_ARC_DEG:g})")
    tcp_mark: int | None = Field(None, ge=1, le=49, description="step number of the recorded mark to turn at "
                                                               "(default: the one nearest the marks' centre)")
    clearance_mm: float = Field(30.0, ge=0, le=500, description="height the tool is lifted by to leave and "
                                                               "approach the mark for the turn, mm")
    speed_m_s: float | None = Field(None, ge=0.001, le=2.0, description="tool speed of the turn's moves, m/s "
                                                                    "(default: calibration.speed_m_s)")

    @field_validator("tcp_angles_deg")
    @classmethod
    def _angles(cls, v: list[float]) -> list[float]:
        if any(not -180.0 <= a <= 180.0 for a in v):
            raise ValueError("each angle must lie within -180..180 degrees")
        a = sorted(set(v))
        if len(a) < MIN_ANGLES:
            raise ValueError(f"{len(a)} distinct angle(s); a circle needs at least {MIN_ANGLES}")
        if a[-1] - a[0] < MIN_ARC_DEG:
            raise ValueError(f"the angles span {a[-1] - a[0]:g} deg; give at least {MIN_ARC_DEG:g} (90-180 is best)")
        return a


def choose_marks(target: Target, found_ids: list[int], n: int) -> list[int]:
    """``n`` found mark ids spread over the plate: corners, edge midpoints, centre, then more."""
    rows = getattr(target, "rows", 0)
    cols = getattr(target, "cols", 0)
    found = set(found_ids)
    preferred: list[int] = []
    if rows and cols:
        side = int(np.ceil(np.sqrt(n)))
        rr = np.linspace(0, rows - 1, max(side, 2)).round().astype(int)
        cc = np.linspace(0, cols - 1, max(side, 2)).round().astype(int)
        preferred = [int(r * cols + c) for r in rr for c in cc]
    ordered = [i for i in dict.fromkeys(preferred) if i in found] + [i for i in found_ids if i not in preferred]
    if len(ordered) < n:
        raise RoutineError(f"only {len(ordered)} marks are visible; {n} are needed — put the whole plate in view")
    return ordered[:n]


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    d = services.config.calibration
    camera_id, robot_id = p.camera_id or d.camera, p.robot_id or d.robot
    tname, target = routine_target(services, p.target)
    if p.tool_centre and d.setup == "eye-in-hand":
        raise RoutineError("tool_centre needs a fixed camera that sees the gripper (calibration.setup: eye-to-hand); "
                           "a camera on the tool turns with it")
    if p.tcp_mark is not None and p.tcp_mark > p.marks:
        raise RoutineError(f"tcp_mark {p.tcp_mark}: only {p.marks} marks will be recorded; give 1..{p.marks}")
    cam, robot = devices(services, camera_id, robot_id)
    if robot is None:
        raise RoutineError(f"routine needs robot {robot_id!r}; name a configured robot (robot_id)")
    shot = capture(cam, robot, target, "marks", ctx)
    if not shot.detection.found:
        raise RoutineError(f"the marks are not seen ({shot.detection.reason}); put the plate in view and start again")
    ids = [int(i) for i in shot.detection.ids]
    chosen = choose_marks(target, ids, p.marks)
    uv_of = {int(i): shot.detection.uv[k] for k, i in enumerate(shot.detection.ids)}
    cols = getattr(target, "cols", 1) or 1
    marks = [{"step": k + 1, "mark_id": i, "row": i // cols, "col": i % cols,
              "u_px": float(uv_of[i][0]), "v_px": float(uv_of[i][1])} for k, i in enumerate(chosen)]
    ctx.report(0.05, f"{len(marks)} marks to record", marks=marks)
    pairs = []
    poses: list[np.ndarray] = []
    for k, mark in enumerate(marks):
        instruction = (f"jog the tool tip onto mark {mark['step']} (row {mark['row']}, col {mark['col']}) "
                       "and press record")
        while True:
            got = ctx.wait_input({**mark, "of": len(marks), "marks": marks, "instruction": instruction},
                                 timeout_s=p.step_timeout_s)
            try:
                with robot_still(ctx, robot, f"jog-to-mark: recording mark {mark['step']}"):
                    T = robot.state().T_base_tool
                break
            except (RobotBusy, RobotStopped) as exc:  # a jog still moving, or latched: the pose is not the mark's
                ctx.report(0.05 + k / len(marks) * (0.55 if p.tool_centre else 0.85), f"not recorded: {exc}")
                instruction = f"not recorded: {exc}; when the robot stands on mark {mark['step']}, press record"
        if "x_mm" in got and "y_mm" in got:
            x_mm, y_mm = float(got["x_mm"]), float(got["y_mm"])
        else:
            x_mm, y_mm = float(T[0, 3] * 1e3), float(T[1, 3] * 1e3)
        poses.append(T)
        pairs.append({**mark, "x_mm": x_mm, "y_mm": y_mm, "recorded_by": got.get("who", ctx.started_by)})
        share = 0.55 if p.tool_centre else 0.85
        ctx.report(0.05 + share * (k + 1) / len(marks), f"mark {k + 1}/{len(marks)} recorded",
                   recorded=k + 1, x_mm=x_mm, y_mm=y_mm)
    found = active_camera(services, camera_id) if p.undistort else None
    camera = found[1] if found is not None else None
    uv = np.array([[m["u_px"], m["v_px"]] for m in pairs])
    xy = np.array([[m["x_mm"], m["y_mm"]] for m in pairs])
    result = fit_npoint(uv, xy, p.model, camera)
    np_json = result.to_json()
    if shot.T_base_tool is None:
        raise RoutineError("the capture has no robot pose; the robot must report its pose")
    np_json["capture_pose_ur"] = [float(v) for v in g.transform_to_ur_pose(shot.T_base_tool)]
    np_json["target"] = tname
    np_json["verdict"] = assess_npoint(result, uv, xy, shot.frame.size, [m["step"] for m in pairs])
    if p.tool_centre:
        step = p.tcp_mark or _central_step(pairs)
        T_mark = poses[step - 1].copy()
        T_mark[:2, 3] = [pairs[step - 1]["x_mm"] * 1e-3, pairs[step - 1]["y_mm"] * 1e-3]
        ctx.report(0.62, f"turning the tool at mark {step} for the tool centre")
        plan = TurnPlan(T_mark, step, p.tcp_angles_deg, p.clearance_mm * 1e-3, p.speed_m_s or d.speed_m_s)
        np_json["tool_centre"] = run_turn(services, ctx, robot, cam, plan, result, (0.62, 0.95))
    record = services.store.save_calibration(
        "npoint", camera_id, robot_id, np_json, {"pairs": pairs, "image_size": list(shot.frame.size)},
        creator=ctx.started_by, note=p.note or f"jog-to-mark, {len(pairs)} marks")
    return {"calibration_id": record.id, "version": record.version, "kind": "npoint", "model": np_json["model"],
            "rms_mm": np_json["rms_mm"], "loo_rms_mm": np_json["loo_rms_mm"],
            "field_sigma_mm": np_json["field_sigma_mm"], "affine": np_json["affine"],
            "residuals_mm": np_json["residuals_mm"], "pairs": pairs, "verdict": np_json["verdict"],
            "tool_centre": np_json.get("tool_centre"), "activated": False}


def _central_step(pairs: list[dict[str, Any]]) -> int:
    """Step number of the recorded mark nearest the marks' centroid (robot x/y)."""
    xy = np.array([[m["x_mm"], m["y_mm"]] for m in pairs])
    return int(np.argmin(np.linalg.norm(xy - xy.mean(axis=0), axis=1))) + 1
