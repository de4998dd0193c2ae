"""``conveyor-calibrate``: the belt's direction in the robot's base frame and its encoder's ticks per metre.

A target rides the belt (in the virtual conveyor cell: the chessboard ``belt_board``) past the camera,
which is calibrated and fixed (an active camera calibration and an eye-to-hand hand-eye give
``T_base_cam``). Each frame where the target is found gives its origin in the base frame at the
encoder count latched at the frame's exposure (``Frame.meta["encoder_ticks"]``); the origin's
positions against the counts are fitted with a straight line (least squares, per axis): its slope is
metres per tick. ``direction_base`` is the slope's unit vector, ``ticks_per_m`` one over its length;
their 1-sigma uncertainties come from the fit's residuals (``sigma_ticks_per_m``, and the angle
``sigma_direction_deg`` of the slope's uncertainty across the direction). The belt must move (the
routine says so when the count does not change); the robot does not move and must not hide the
target. The result is stored as a calibration of kind ``conveyor`` keyed by the conveyor's id (in
place of a camera's) and the robot's id, not activated (``POST /calibrations/{id}/activate``).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration.detect import detect
from calibration.io import handeye_camera
from calibration.pose import estimate_pose
from cellctl.jobs import JobContext
from cellctl.mapping import NoCalibration, active_camera
from cellctl.routines.common import RoutineError, detected_points_m, routine_target
from cellctl.services import Services

MAX_SIGMA_RELATIVE = 0.002
"""The verdict is not ok when ``sigma_ticks_per_m`` exceeds this share of ``ticks_per_m``."""
MAX_SIGMA_DIRECTION_DEG = 0.2


class Params(BaseModel):
    """Parameters of ``conveyor-calibrate`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="ConveyorCalibrateParams")

    conveyor_id: str | None = Field(None, description="the belt (default: the config's first conveyor)")
    camera_id: str | None = Field(None, description="the fixed camera (default: calibration.camera)")
    robot_id: str | None = Field(None, description="the robot whose base frame (default: calibration.robot)")
    target: str = Field("belt_board", description="the config's target that rides the belt")
    sightings: int = Field(8, ge=2, le=200, description="frames with the target to fit")
    min_travel_mm: float = Field(150.0, gt=0, le=10000, description="the target must travel at least this far "
                                                                    "between the first and the last sighting, mm")
    timeout_s: float = Field(90.0, gt=0, le=3600, description="give up when the sightings are not taken by then, s")


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    d = services.config.calibration
    camera_id, robot_id = p.camera_id or d.camera, p.robot_id or d.robot
    conveyors = sorted(services.config.conveyors)
    conveyor_id = p.conveyor_id or (conveyors[0] if conveyors else None)
    if conveyor_id is None or conveyor_id not in services.config.conveyors:
        raise RoutineError(f"no conveyor {conveyor_id!r} in the config's conveyors ({conveyors}): name the belt")
    conveyor = services.cell.conveyor(conveyor_id).ensure_open()
    _, target = routine_target(services, p.target)
    found = active_camera(services, camera_id)
    he = services.store.active("handeye", camera_id, robot_id)
    if found is None or he is None or he.result.get("setup") != "eye-to-hand":
        raise NoCalibration(f"camera {camera_id} needs an active camera calibration and an active eye-to-hand "
                            f"hand-eye calibration with robot {robot_id} before the belt is calibrated against it")
    camera = handeye_camera(he.result, f"hand-eye calibration {he.id}") or found[1]
    T_base_cam = np.asarray(he.result["T_base_cam"], dtype=np.float64)
    cam = services.cell.camera(camera_id).ensure_open()
    ticks0 = conveyor.ticks()
    rows: list[dict[str, Any]] = []
    t_end = time.monotonic() + p.timeout_s
    ctx.report(0.05, f"waiting for {p.target} on the belt")
    while time.monotonic() < t_end:
        ctx.check_cancelled()
        frame = cam.grab(timeout_s=5.0)
        ticks = frame.metadata.get("encoder_ticks")
        if ticks is None:
            raise RoutineError(f"camera {camera_id}'s frames carry no encoder count (Frame.meta['encoder_ticks']): "
                               "the count must be latched at each exposure (docs/conveyor.md)")
        det = detect(frame.pixels, target)
        if not det.found:
            if len(rows) >= 3 and _travel_mm(rows) >= p.min_travel_mm:
                break  # it has left the view after enough travel
            if rows and int(ticks) != rows[-1]["ticks"]:
                rows = []  # it left the view too soon: the next pass (a belt is a loop) starts afresh
            continue
        X = detected_points_m(target, det)
        pose = estimate_pose(camera, X, det.uv)
        T_base_target = T_base_cam @ pose.T_cam_target
        rows.append({"ticks": int(ticks), "origin_m": T_base_target[:3, 3].tolist(), "rms_px": pose.rms_px})
        ctx.report(min(0.9, 0.1 + 0.8 * len(rows) / p.sightings), f"{len(rows)} sighting(s)")
        if len(rows) >= p.sightings and _travel_mm(rows) >= p.min_travel_mm:
            break
    if conveyor.ticks() == ticks0:
        raise RoutineError(f"the encoder count of {conveyor_id} did not change: start the belt (the routine needs it "
                           "moving) and calibrate again")
    if len(rows) < 3 or _travel_mm(rows) < p.min_travel_mm:
        raise RoutineError(f"{len(rows)} sighting(s) of {p.target} over {_travel_mm(rows):.0f} mm in "
                           f"{p.timeout_s:g} s: need 3 or more over {p.min_travel_mm:g} mm; put the target on the "
                           "belt upstream of the camera and calibrate again")
    result = fit_belt(np.array([r["ticks"] for r in rows], dtype=np.float64),
                      np.array([r["origin_m"] for r in rows], dtype=np.float64))
    record = services.store.save_calibration("conveyor", conveyor_id, robot_id, result,
                                             {"sightings": rows, "camera_id": camera_id, "target": p.target,
                                              "handeye_calibration_id": he.id}, ctx.started_by,
                                             note=f"conveyor-calibrate: {len(rows)} sightings")
    ctx.report(1.0, "stored (not active)")
    return {"calibration_id": record.id, "version": record.version, "kind": "conveyor", **result}


def _travel_mm(rows: list[dict[str, Any]]) -> float:
    if len(rows) < 2:
        return 0.0
    return float(np.linalg.norm(np.subtract(rows[-1]["origin_m"], rows[0]["origin_m"]))) * 1e3


def fit_belt(ticks: np.ndarray, origins_m: np.ndarray) -> dict[str, Any]:
    """The belt from a point's base-frame positions (N x 3, m) at encoder counts (N): the line's slope
    (m per tick) gives ``direction_base`` and ``ticks_per_m``; their 1-sigma from the fit's residuals."""
    c = ticks - ticks.mean()
    sxx = float(c @ c)
    if sxx <= 0:
        raise RoutineError("every sighting has the same encoder count: the belt (or its encoder) did not move")
    slope = (c @ (origins_m - origins_m.mean(axis=0))) / sxx  # (3,) m per tick
    resid = origins_m - origins_m.mean(axis=0) - np.outer(c, slope)
    dof = max(1, len(ticks) - 2)
    sigma_axis = np.sqrt((resid**2).sum(axis=0) / dof / sxx)  # 1-sigma of each slope component
    length = float(np.linalg.norm(slope))
    direction = slope / length
    sigma_along = float(np.sqrt(((direction * sigma_axis) ** 2).sum()))
    across = np.sqrt(max(0.0, float((sigma_axis**2).sum()) - sigma_along**2))
    tpm = 1.0 / length
    sigma_tpm = sigma_along / length**2
    sigma_dir_deg = float(np.degrees(np.arctan2(across, length)))
    problems = []
    if sigma_tpm > MAX_SIGMA_RELATIVE * tpm:
        problems.append({"code": "ticks_per_m_uncertain", "message": f"ticks_per_m is known to {sigma_tpm:.1f} "
                         f"(1-sigma) of {tpm:.1f}: let the target travel further or take more sightings"})
    if sigma_dir_deg > MAX_SIGMA_DIRECTION_DEG:
        problems.append({"code": "direction_uncertain", "message": f"the direction is known to {sigma_dir_deg:.2f} "
                         "deg: let the target travel further or take more sightings"})
    rms_mm = float(np.sqrt((resid**2).sum(axis=1).mean())) * 1e3
    return {"direction_base": direction.tolist(), "ticks_per_m": tpm, "sigma_ticks_per_m": sigma_tpm,
            "sigma_direction_deg": sigma_dir_deg, "rms_mm": rms_mm, "n_sightings": len(ticks),
            "travel_mm": float(np.ptp(c) * length * 1e3), "verdict": {"ok": not problems, "problems": problems}}
