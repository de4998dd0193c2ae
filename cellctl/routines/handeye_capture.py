"""``handeye-capture``: robot stations chosen from what was captured, until the hand-eye verdict is ok.

Each next station is the most informative reachable one (``station_plan.StationPlanner``:
rotations about well-separated axes, the plate in view, distances varied). Every move goes through
the robot's own checks (envelope, tool cone, speed) in the routine's motion session; a refused
move is skipped with its reason. Once ``stations`` good stations cover the rotation and distance
goals, the hand-eye is solved; while its verdict is not ok and the ``max_stations`` budget lasts,
stations are added and it is solved again. The result says what coverage is still missing. Uses
the active camera calibration of the camera; stores, does not activate. With ``dof: 4`` (a robot
that only turns the tool about base z) the stations turn and shift instead of tilting, and the
plate's height ``target_z_mm`` fixes what such motion cannot observe (``handeye_dof4_capture``).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from calibration.handeye import HandEyeError, HandEyeResult, calibrate_handeye
from calibration.intrinsics import param_names
from cellctl.jobs import JobContext
from cellctl.mapping import active_camera
from cellctl.routines.common import (
    Capture,
    RoutineError,
    capture,
    detection_inputs,
    devices,
    move,
    routine_target,
    stop_robot_on_end,
    target_pose,
)
from cellctl.routines.handeye_dof4_capture import run_dof4, store_dof4
from cellctl.routines.station_plan import Coverage, StationPlanner
from cellctl.services import Services
from drivers.base import MotionRejected
from drivers.robot_base import turn_deg

RESOLVE_EVERY = 2
"""After a verdict that is not ok, solve again once this many more stations are in."""
DOF4_HINT = (" For a SCARA / top-down-only cell, run handeye-capture with dof 4 and target_z_mm (the plate "
             "origin's height in the robot base frame, mm).")
"""The routine's way to the solver's alternative (``HandEyeError.alternative == "dof4"``)."""
CARRIED_MIN_TURN_DEG = 5.0
"""A station whose tool turned at least this much from the start must turn the plate in the camera's view."""


class Params(BaseModel):
    """Parameters of ``handeye-capture`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="HandeyeCaptureParams")

    camera_id: str | None = Field(None, description="camera to calibrate (default: the config's calibration.camera)")
    robot_id: str | None = Field(None, description="robot to use (default: the config's calibration.robot)")
    target: str | None = Field(None, description="name of a target in the config's targets "
                                                 "(default: calibration.target)")
    setup: Literal["eye-in-hand", "eye-to-hand"] | None = Field(
        None, description="where the camera is: eye-in-hand (on the tool, plate on the table) or eye-to-hand "
                          "(fixed, plate held by the tool); default: the config's calibration.setup")
    stations: int = Field(10, ge=4, le=40, description="good stations to collect before the first verdict, "
                                                       "including the start pose")
    max_stations: int = Field(24, ge=4, le=80, description="most stations to try, the start pose included "
                                                           "(rejected shots and refused moves count); the routine "
                                                           "adds stations until the hand-eye verdict is ok or this "
                                                           "budget is spent")
    max_tilt_deg: float = Field(25.0, ge=5, le=45, description="largest tilt about the plate's centre, degrees "
                                                               "(the checks ask for relative rotations of 15-30)")
    max_spin_deg: float = Field(40.0, ge=0, le=90, description="largest spin about the line of sight, degrees")
    distance_range: float = Field(0.15, ge=0, le=0.4, description="stations at the start distance times 1 +/- "
                                                                  "this fraction; the distances must span it")
    min_point_fraction: float = Field(0.8, gt=0, le=1, description="a station counts when at least this "
                                                                   "fraction of the target's points is detected")
    speed_m_s: float | None = Field(None, ge=0.001, le=2.0, description="tool speed, m/s, 0.001-2 "
                                                                    "(default: calibration.speed_m_s)")
    note: str = Field("", max_length=500, description="note stored with the calibration")
    dof: Literal[4, 6] = Field(6, description="6: the robot turns the tool freely (stations tilt about the plate); "
                                              "4: a SCARA, delta or top-down robot that only turns the tool about "
                                              "the base z axis (stations turn about z by up to max_spin_deg and "
                                              "move in x, y, z; max_tilt_deg is not used); needs target_z_mm")
    target_z_mm: float | None = Field(None, ge=-1e4, le=1e4,
                                      description="dof 4: the plate origin's height in the robot base frame, mm "
                                                  "(eye-to-hand: at the start pose); it fixes what a robot turning "
                                                  "only about z cannot observe",
                                      json_schema_extra={"x-default": "none (dof 4 needs it)"})


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    if p.stations > p.max_stations:
        raise RoutineError(f"stations ({p.stations}) is more than the max_stations budget ({p.max_stations}); "
                           "raise max_stations or lower stations")
    defaults = services.config.calibration
    camera_id = p.camera_id or defaults.camera
    robot_id = p.robot_id or defaults.robot
    setup = p.setup or defaults.setup
    tname, target = routine_target(services, p.target)
    n_points = len(target.points().ids)
    found = active_camera(services, camera_id)
    if found is None:
        raise RoutineError(f"camera {camera_id} has no active calibration; run the intrinsics-capture routine "
                           "(POST /routines/intrinsics-capture) and activate its result "
                           "(POST /calibrations/{id}/activate) first")
    active, camera = found
    cam, robot = devices(services, camera_id, robot_id)
    if robot is None:
        raise RoutineError(f"routine needs robot {robot_id!r}; name a configured robot (robot_id)")
    stop_robot_on_end(ctx, robot)

    def good(c: Capture) -> bool:
        return c.detection.found and len(c.detection.ids) >= p.min_point_fraction * n_points

    first = capture(cam, robot, target, "station01", ctx)
    if not good(first):
        raise RoutineError(f"the plate is not seen from the start pose ({first.detection.reason or 'too few points'}"
                           "); move the robot (POST /robots/{id}/move) so the whole plate is in view, then start "
                           "again")
    if first.T_base_tool is None:
        raise RoutineError("the start view has no robot pose; the robot must report its pose")
    speed = p.speed_m_s or defaults.speed_m_s
    if p.dof == 4:
        he, caps4, counts4 = run_dof4(services, ctx, p, setup, camera, target, cam, robot, first, good, speed)
        return store_dof4(services, ctx, p, he, caps4, tname, active.id, camera_id, robot_id, counts4)
    planner = StationPlanner(setup, camera, target, first.T_base_tool, target_pose(camera, target, first.detection),
                             robot.limits.check_pose, p.max_tilt_deg, p.max_spin_deg, p.distance_range)
    caps: list[Capture] = [first]
    camera_ok = (active.result.get("verdict") or {}).get("ok")
    camera_cov = camera_covariance(active.result, camera.model)
    tried, rejected = 1, 0
    refused: list[dict[str, str]] = []
    left_out: dict[str, int] = {}
    result: HandEyeResult | None = None
    failure = ""
    solved_at = 0
    ctx.report(0.02, "station 1: ok (start pose)")

    def solve() -> None:
        nonlocal result, failure, solved_at
        ctx.check_cancelled()
        ctx.report(min(0.9, tried / p.max_stations), f"solving hand-eye from {len(caps)} stations")
        solved_at = len(caps)
        try:
            poses = [c.T_base_tool for c in caps if c.T_base_tool is not None]  # every station has one
            result = calibrate_handeye(setup, poses, [c.detection for c in caps], camera, target,
                                       camera_verdict_ok=camera_ok, camera_covariance=camera_cov)
            failure = ""
        except HandEyeError as exc:
            result, failure = None, str(exc) + (DOF4_HINT if exc.alternative == "dof4" else "")

    while True:
        cov = planner.coverage(p.stations)
        if not cov.missing and (solved_at == 0 or len(caps) - solved_at >= RESOLVE_EVERY):
            solve()
            if result is not None and _ok(result):
                break
        if tried >= p.max_stations:
            break
        cand, why = planner.next()
        for k, n in why.items():
            left_out[k] = max(left_out.get(k, 0), n)
        if cand is None:
            break
        tried += 1
        try:
            move(services, ctx, robot, cand.T_base_tool, speed, f"handeye-capture {cand.purpose}")
        except MotionRejected as exc:
            refused.append({"station": cand.purpose, "reason": str(exc)})
            planner.failed_at(cand.T_base_tool)
            ctx.report(min(0.9, tried / p.max_stations), f"station {tried} ({cand.purpose}): skipped, refused ({exc})")
            continue
        c = capture(cam, robot, target, f"station{tried:02d}", ctx)
        ok = good(c) and c.T_base_tool is not None
        if ok and c.T_base_tool is not None:
            T_cam_target = target_pose(camera, target, c.detection)
            check_carried(first.T_base_tool, target_pose(camera, target, first.detection), c.T_base_tool,
                          T_cam_target, setup, cand.purpose)
            caps.append(c)
            planner.observe(c.T_base_tool, T_cam_target, cand.purpose)
        else:
            rejected += 1
            planner.failed_at(cand.T_base_tool)
        cov = planner.coverage(p.stations)
        ctx.report(min(0.9, tried / p.max_stations), f"station {tried} ({cand.purpose}): "
                   + ("ok" if ok else f"rejected ({c.detection.reason or 'too few points'})"),
                   rotation_axis_spread_deg=round(cov.axis_spread_deg, 1), coverage_missing=cov.missing)
    returned = ""
    try:
        move(services, ctx, robot, first.T_base_tool, speed, "handeye-capture: back to start")
    except MotionRejected as exc:  # the calibration does not depend on it: say so, keep the stations
        returned = f"the move back to the start pose was refused ({exc}); the robot is at the last station"
        ctx.report(0.9, returned)
    cov = planner.coverage(p.stations)
    if result is None or solved_at != len(caps):
        solve()
    if result is None:
        raise RoutineError(f"hand-eye cannot be solved from the {len(caps)} stations captured ({failure}); "
                           + _advice(cov, tried, p.max_stations))
    return _store(services, ctx, p, result, caps, cov, tname, active.id, camera_id, robot_id,
                  {"stations_tried": tried, "stations_rejected": rejected, "stations_refused": refused,
                   "candidates_left_out": left_out, "returned_to_start": not returned,
                   "camera_covariance_used": camera_cov is not None,
                   **({"warning": returned} if returned else {})})


def check_carried(T_base_tool0: NDArray[np.float64], T_cam_target0: NDArray[np.float64],
                  T_base_tool: NDArray[np.float64], T_cam_target: NDArray[np.float64], setup: str,
                  purpose: str) -> None:
    """Refuse stations where the plate, seen from the camera, did not turn as the tool turned.

    Whichever the robot carries (the camera or the plate), the plate turns in the camera's frame
    by the tool's angle (hand-eye's AX = XB keeps rotation angles). When the tool turned by at least
    ``CARRIED_MIN_TURN_DEG`` and the plate by less than half of that, the robot carries neither: a
    plate lying still in front of a fixed camera has no hand-eye (jog-to-mark maps that camera).
    """
    tool_deg = turn_deg(T_base_tool0, T_base_tool)
    plate_deg = turn_deg(T_cam_target0, T_cam_target)
    if tool_deg >= CARRIED_MIN_TURN_DEG and plate_deg < 0.5 * tool_deg:
        where = ("the plate must ride on the tool, facing the camera" if setup == "eye-to-hand"
                 else "the camera must ride on the tool")
        raise RoutineError(f"the tool turned {tool_deg:.1f} deg from the start pose ({purpose}) but the plate, seen "
                           f"from the camera, turned {plate_deg:.1f} deg: the robot carries neither the camera nor "
                           f"the plate, and {where} (setup: {setup}). A camera fixed over a plate that lies still is "
                           "mapped to the robot with jog-to-mark (POST /routines/jog-to-mark)")


def _ok(result: HandEyeResult) -> bool:
    """The verdict is ok and no problem asks for more or better stations."""
    verdict = result.to_json()["verdict"]
    return bool(verdict["ok"]) and not any(q["code"] in ("few_poses", "low_axis_spread") for q in verdict["problems"])


def _advice(cov: Coverage, tried: int, budget: int) -> str:
    missing = "; ".join(cov.missing) or "nothing in the coverage"
    if tried >= budget:
        return f"still missing: {missing}. Raise max_stations (spent {tried} of {budget})"
    return (f"still missing: {missing}. No reachable station was left: widen max_tilt_deg, max_spin_deg or "
            "distance_range, or start from a pose with more room in the robot's envelope")


def camera_covariance(cam_json: dict[str, Any], model: str) -> NDArray[np.float64] | None:
    """The active camera calibration's intrinsics covariance (``parameters``: names + covariance) in
    the hand-eye's order (fx, fy, cx, cy, the model's distortion coefficients), or None when it has
    none; it enters the hand-eye's uncertainty (as ``calib handeye`` does with cam.json)."""
    params: Any = cam_json.get("parameters")
    try:
        names = list(params["names"])
        cov = np.asarray(params["covariance"], dtype=np.float64)
    except (TypeError, KeyError, ValueError):
        return None
    want = param_names(model)
    if cov.shape != (len(names), len(names)) or not set(names) <= set(want) or not np.all(np.isfinite(cov)):
        return None
    idx = [want.index(n) for n in names]
    full = np.zeros((len(want), len(want)))
    full[np.ix_(idx, idx)] = cov
    return full


def _store(services: Services, ctx: JobContext, p: Params, result: HandEyeResult, caps: list[Capture],
           cov: Coverage, tname: str, camera_calibration_id: int, camera_id: str, robot_id: str,
           counts: dict[str, Any]) -> dict[str, Any]:
    ctx.check_cancelled()
    he = result.to_json()
    he["camera_calibration_id"] = camera_calibration_id
    he["target"] = tname
    complete = _ok(result) and not cov.missing
    he["verdict"]["coverage"] = cov.to_json()
    he["verdict"]["coverage_missing"] = cov.missing
    if cov.missing:
        he["verdict"]["problems"].append({
            "code": "coverage_missing", "severity": "warning",
            "message": "the stations lack " + "; ".join(cov.missing) + ": run handeye-capture again with a larger "
                       "max_stations, or more room (max_tilt_deg, max_spin_deg, distance_range, the envelope)"})
    record = services.store.save_calibration(
        "handeye", camera_id, robot_id, he,
        {"target": services.config.targets[tname], "camera_calibration_id": camera_calibration_id,
         "stations": detection_inputs(caps)},
        creator=ctx.started_by, note=p.note or f"handeye-capture, {len(caps)} stations")
    name = "T_tool_cam" if result.setup == "eye-in-hand" else "T_base_cam"
    ctx.report(1.0, "hand-eye verdict ok" if complete else
               "budget spent: " + ("; ".join(cov.missing) or "verdict not ok"))
    return {"calibration_id": record.id, "version": record.version, "kind": "handeye", "setup": result.setup,
            name: he[name], "rms_px": he["rms_px"],
            "loo_prediction_rms_px": he["quality"]["loo_prediction_rms_px"],
            "uncertainty": {k: he["uncertainty"][k] for k in ("rot_deg", "trans_mm")},
            "stations_used": len(caps), **counts, "stations_unreachable": len(counts["stations_refused"]),
            "coverage": cov.to_json(), "complete": complete, "verdict": he["verdict"], "activated": False}

