"""jog-to-mark's tool-centre step: turn the tool about z at one recorded mark, fit the circle.

With a fixed camera the operator jogs a feature of the gripper onto each mark, but the robot
reports its flange axis. At one mark (the recorded pose of its step) the routine turns the tool
about the base z axis — the tool's own axis when it points down — through the given angles; at
each, the camera sees the feature (``calibration.detect.tool_spot``: a saturated spot ringed by dark)
and the robot reports its flange. ``calibration.handeye.tool_centre`` fits the circle through the N-point map:
the feature's offset from the flange axis, with its 1-sigma and residual.

Motion: the routine takes the robot's motion for the step only (the operator jogged it freely
before), so a second mover is refused, every move is checked (envelope, tool cone, speed) and
audited, and a Stop aborts the job (it ends ``stopped``, nothing stored). The tool leaves the
last mark upwards by ``clearance_mm``, comes down onto the chosen mark, turns, turns back and
lifts again; the robot is halted when the job ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.detect import SpotNotFound, find_spot
from calibration.handeye import fit_tool_centre, tool_offset_vector
from calibration.npoint import NPointResult
from cellctl.jobs import JobContext
from cellctl.routines.common import RoutineError, move, robot_still, stop_robot_on_end
from cellctl.services import Services
from drivers.base import CameraBase, RobotBase

Mat4 = NDArray[np.float64]


@dataclass
class TurnPlan:
    T_mark: Mat4
    """Recorded flange pose (base frame, m) at the chosen mark; the angles turn about its z."""
    step: int
    angles_deg: list[float]
    clearance_m: float
    speed_m_s: float


def turned(T: Mat4, angle_deg: float) -> Mat4:
    """``T`` turned about the base z axis through its own position by ``angle_deg`` (CCW from above)."""
    out = np.asarray(T, dtype=np.float64).copy()
    out[:3, :3] = g.rotvec_to_matrix([0.0, 0.0, np.radians(angle_deg)]) @ out[:3, :3]
    return out


def lifted(T: Mat4, dz_m: float) -> Mat4:
    out = np.asarray(T, dtype=np.float64).copy()
    out[2, 3] += dz_m
    return out


def yaw_deg(R_from: NDArray[np.float64], R_to: NDArray[np.float64]) -> float:
    """Angle (deg, CCW seen from above) of the base-z turn from ``R_from`` to ``R_to``."""
    M = np.asarray(R_to) @ np.asarray(R_from).T
    return float(np.degrees(np.arctan2(M[1, 0], M[0, 0])))


def run_turn(services: Services, ctx: JobContext, robot: RobotBase, cam: CameraBase, plan: TurnPlan,
             npoint: NPointResult, progress: tuple[float, float]) -> dict[str, Any]:
    """Turn at the mark, see the feature at each angle, fit the tool centre; its JSON (``calib tcp``'s
    keys plus ``rotations``, ``offset_tool_m`` and the orientation at ``rz = 0``)."""
    session = robot.motion.begin(ctx.started_by, "routine jog-to-mark: tool-centre turn")
    ctx.motion = session
    stop_robot_on_end(ctx, robot)
    p0, p1 = progress
    rows: list[dict[str, float]] = []
    try:
        here = robot.state().T_base_tool
        move(services, ctx, robot, lifted(here, plan.clearance_m), plan.speed_m_s, "jog-to-mark: lift off the mark")
        move(services, ctx, robot, lifted(plan.T_mark, plan.clearance_m), plan.speed_m_s,
             f"jog-to-mark: above mark {plan.step}")
        move(services, ctx, robot, plan.T_mark, plan.speed_m_s, f"jog-to-mark: onto mark {plan.step}")
        R_mark = plan.T_mark[:3, :3]
        for k, angle in enumerate(plan.angles_deg):
            move(services, ctx, robot, turned(plan.T_mark, angle), plan.speed_m_s,
                 f"jog-to-mark: tool turned {angle:g} deg at mark {plan.step}")
            ctx.check_cancelled()
            with robot_still(ctx, robot, f"jog-to-mark: tool-centre turn at {angle:g} deg"):
                T = robot.state().T_base_tool
                frame = cam.grab(timeout_s=5.0)
            try:
                spot = find_spot(frame.pixels)
            except SpotNotFound as exc:
                raise RoutineError(f"tool-centre turn, {angle:g} deg: {exc}") from None
            rows.append({"u_px": spot.u_px, "v_px": spot.v_px, "x_mm": float(T[0, 3] * 1e3),
                         "y_mm": float(T[1, 3] * 1e3), "rz_deg": yaw_deg(R_mark, T[:3, :3])})
            ctx.report(p0 + (p1 - p0) * (k + 1) / len(plan.angles_deg),
                       f"tool-centre turn: angle {k + 1}/{len(plan.angles_deg)} ({angle:g} deg) seen",
                       turn_angle=k + 1, **rows[-1])
        move(services, ctx, robot, plan.T_mark, plan.speed_m_s, "jog-to-mark: tool turned back")
        move(services, ctx, robot, lifted(plan.T_mark, plan.clearance_m), plan.speed_m_s,
             "jog-to-mark: lift off the mark")
    finally:
        ctx.motion = None
        robot.motion.end(session)
    arr = np.array([[r["u_px"], r["v_px"], r["x_mm"], r["y_mm"], r["rz_deg"]] for r in rows])
    try:
        res = fit_tool_centre(arr[:, 0:2], arr[:, 2:4], arr[:, 4], npoint)
    except ValueError as exc:
        raise RoutineError(f"tool centre: {exc}") from None
    out = res.to_json()
    out["rotations"] = rows
    out["mark_step"] = plan.step
    out["rz0_tool_rotvec_rad"] = [float(v) for v in g.matrix_to_rotvec(plan.T_mark[:3, :3])]
    out["offset_tool_m"] = tool_offset_vector(res.offset_mm, plan.T_mark[:3, :3]).tolist()
    return out
