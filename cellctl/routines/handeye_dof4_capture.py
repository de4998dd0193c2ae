"""``handeye-capture`` with ``dof: 4``: stations for a robot that only turns its tool about base z.

A SCARA, a delta or a top-down picking arm cannot tilt the tool, so the 6-DOF planner's stations
(tilts about the plate's centre) are out of its reach. Here every station is the start pose
turned about the vertical line through the plate's estimated centre (base frame) by up to
``max_spin_deg``, and moved in x/y (a tenth of the plate distance) and in z (the start distance
times ``distance_range``), in an order that mixes both turn directions with the shifts. The plate's
centre is estimated with the camera frame at the tool's (eye-in-hand) or the plate's frame at the
tool's (eye-to-hand): a station whose plate leaves the view is rejected and the next is tried.
The hand-eye is solved by ``calibration.handeye.dof4`` with the plate's height ``target_z_mm``
(base frame, mm), which fixes the part of the transform such motion cannot observe. Metres,
degrees.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.handeye import HandEyeError, calibrate_handeye_dof4
from calibration.targets import Target
from cellctl.hints import ROUTINE, handeye_message
from cellctl.jobs import JobContext
from cellctl.routines.common import Capture, RoutineError, capture, detection_inputs, move, target_pose
from cellctl.services import Services
from drivers.base import MotionRejected, RobotBase

Mat4 = NDArray[np.float64]
TURN_FRACTIONS = (0.5, -0.5, 1.0, -1.0, 0.25, -0.75, 0.75, -0.25)
SHIFTS = ((1, 0, 0), (0, 1, 0), (-1, 0, 1), (0, -1, -1), (1, 1, 0), (-1, -1, 1), (1, -1, -1), (-1, 1, 0))
"""x, y in tenths of the plate distance and z in ``distance_range`` of it, cycled over the turns."""


def dof4_stations(setup: str, T0: Mat4, T_cam_target0: Mat4, centre_target_m: NDArray[np.float64],
                  max_spin_deg: float, distance_range: float, rounds: int = 3) -> list[tuple[str, Mat4]]:
    """Candidate tool poses (purpose, ``T_base_tool``): ``T0`` turned about base z and shifted (module docstring)."""
    # Eye-in-hand: the plate's centre seen with the camera frame at the tool's; eye-to-hand: the tool holds it.
    seen = (T0 @ T_cam_target0 @ np.append(centre_target_m, 1.0))[:3]
    pivot = seen if setup == "eye-in-hand" else T0[:3, 3].copy()
    distance = float(np.linalg.norm(T_cam_target0[:3, 3]))
    out: list[tuple[str, Mat4]] = []
    for r in range(rounds):
        scale = 1.0 - 0.35 * r
        for k, frac in enumerate(TURN_FRACTIONS):
            turn = frac * max_spin_deg * scale
            sx, sy, sz = SHIFTS[(k + 3 * r) % len(SHIFTS)]
            Rz = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, math.radians(turn)]), [0.0, 0.0, 0.0])
            about = g.make_transform(np.eye(3), pivot) @ Rz @ g.make_transform(np.eye(3), -pivot)
            shift = np.array([0.1 * sx * distance, 0.1 * sy * distance, sz * distance_range * distance]) * scale
            T = g.make_transform(np.eye(3), shift) @ about @ T0
            out.append((f"turn {turn:+.0f} deg, shift ({shift[0] * 1e3:+.0f}, {shift[1] * 1e3:+.0f}, "
                        f"{shift[2] * 1e3:+.0f}) mm", T))
    return out


def run_dof4(services: Services, ctx: JobContext, p: Any, setup: str, camera: CameraModel, target: Target,
             cam: Any, robot: RobotBase, first: Capture, good: Callable[[Capture], bool], speed: float
             ) -> tuple[dict[str, Any], list[Capture], dict[str, Any]]:
    """Capture 4-DOF stations and solve; answers (he.json, the captures used, counts)."""
    if p.target_z_mm is None:
        raise RoutineError("dof 4 needs target_z_mm: the plate origin's height in the robot base frame, mm")
    T0 = np.asarray(first.T_base_tool, dtype=np.float64)
    C0 = target_pose(camera, target, first.detection)
    centre = target.points().xyz_m.mean(axis=0)
    candidates = dof4_stations(setup, T0, C0, centre, p.max_spin_deg, p.distance_range)
    caps = [first]
    tried, rejected = 1, 0
    refused: list[dict[str, str]] = []
    he: dict[str, Any] | None = None
    failure = ""

    def solve() -> None:
        nonlocal he, failure
        ctx.check_cancelled()
        ctx.report(min(0.9, tried / p.max_stations), f"solving the 4-DOF hand-eye from {len(caps)} stations")
        try:
            poses = [c.T_base_tool for c in caps if c.T_base_tool is not None]
            he = calibrate_handeye_dof4(setup, poses, [c.detection for c in caps], camera, target,
                                        p.target_z_mm).to_json()
            failure = ""
        except HandEyeError as exc:
            he, failure = None, handeye_message(exc, ROUTINE)

    solved_at = 0
    for purpose, T in candidates:
        if len(caps) >= p.stations and len(caps) - solved_at >= 2:
            solve()
            solved_at = len(caps)
            if he is not None and he["verdict"]["ok"]:
                break
        if tried >= p.max_stations:
            break
        tried += 1
        try:
            robot.limits.check_pose(T)
            move(services, ctx, robot, T, speed, f"handeye-capture dof 4: {purpose}")
        except MotionRejected as exc:
            refused.append({"station": purpose, "reason": str(exc)})
            ctx.report(min(0.9, tried / p.max_stations), f"station {tried} ({purpose}): skipped, refused ({exc})")
            continue
        c = capture(cam, robot, target, f"station{tried:02d}", ctx)
        ok = good(c) and c.T_base_tool is not None
        if ok:
            caps.append(c)
        else:
            rejected += 1
        ctx.report(min(0.9, tried / p.max_stations), f"station {tried} ({purpose}): "
                   + ("ok" if ok else f"rejected ({c.detection.reason or 'too few points'})"))
    returned = ""
    try:
        move(services, ctx, robot, T0, speed, "handeye-capture: back to start")
    except MotionRejected as exc:
        returned = f"the move back to the start pose was refused ({exc}); the robot is at the last station"
    if he is None or solved_at != len(caps):
        solve()
    if he is None:
        raise RoutineError(f"the 4-DOF hand-eye cannot be solved from the {len(caps)} stations captured ({failure}); "
                           "raise max_stations or max_spin_deg, or start from a pose with more room to turn and move")
    counts = {"stations_tried": tried, "stations_rejected": rejected, "stations_refused": refused,
              "returned_to_start": not returned, **({"warning": returned} if returned else {})}
    return he, caps, counts


def store_dof4(services: Services, ctx: JobContext, p: Any, he: dict[str, Any], caps: list[Capture], tname: str,
               camera_calibration_id: int, camera_id: str, robot_id: str, counts: dict[str, Any]) -> dict[str, Any]:
    """Store the 4-DOF result (not activated) and answer the job's result."""
    ctx.check_cancelled()
    he["camera_calibration_id"] = camera_calibration_id
    he["target"] = tname
    record = services.store.save_calibration(
        "handeye", camera_id, robot_id, he,
        {"target": services.config.targets[tname], "camera_calibration_id": camera_calibration_id,
         "target_z_mm": p.target_z_mm, "stations": detection_inputs(caps)},
        creator=ctx.started_by, note=p.note or f"handeye-capture dof 4, {len(caps)} stations")
    name = "T_tool_cam" if he["setup"] == "eye-in-hand" else "T_base_cam"
    ctx.report(1.0, "hand-eye verdict ok" if he["verdict"]["ok"] else "verdict not ok")
    return {"calibration_id": record.id, "version": record.version, "kind": "handeye", "setup": he["setup"],
            "dof": 4, name: he[name], "rms_px": he.get("rms_px"),
            "uncertainty": {k: he["uncertainty"][k] for k in ("rot_deg", "trans_mm")},
            "stations_used": len(caps), **counts, "stations_unreachable": len(counts["stations_refused"]),
            "complete": bool(he["verdict"]["ok"]), "verdict": he["verdict"], "activated": False}
