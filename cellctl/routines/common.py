"""Pieces the calibration routines share: capture a view, plan robot stations, move safely.

Station planning (eye-in-hand, our own): the tool pivots about a point on its z axis at the
distance where the plate was seen, so the plate stays near the same place in the image while
the view direction tilts; lateral offsets move the plate over the image for coverage. Every
planned pose is checked against the robot's envelope before it is used; unreachable ones are
dropped and counted.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.observations import Detection
from calibration.pose import estimate_pose
from calibration.targets import Target, target_from_dict
from cellctl.errors import CellctlError
from cellctl.jobs import JobContext
from cellctl.motion import audited_move
from cellctl.services import Services
from drivers.base import Camera, CameraBase, Frame, MotionRejected, Robot, RobotBase, RobotBusy

Mat4 = NDArray[np.float64]


STILL_WAIT_S = 2.0
"""How long a measurement waits for a robot it owns to report standing still before refusing."""


class RoutineError(CellctlError, ValueError):
    """A routine cannot go on; the message says why and what to do."""


@dataclass
class Capture:
    frame: Frame
    detection: Detection
    T_base_tool: Mat4 | None


def routine_target(services: Services, name: str | None) -> tuple[str, Target]:
    targets = services.config.targets
    tname = name or services.config.calibration.target
    if tname not in targets:
        raise RoutineError(f"no target {tname!r} in the config's targets: {sorted(targets)}")
    return tname, target_from_dict(targets[tname], f"targets.{tname}")


def devices(services: Services, camera_id: str, robot_id: str | None) -> tuple[CameraBase, RobotBase | None]:
    cam = services.cell.camera(camera_id).ensure_open()
    robot = services.cell.robot(robot_id).ensure_open() if robot_id else None
    return cam, robot


@contextlib.contextmanager
def robot_still(ctx: JobContext, robot: Robot | None, what: str) -> Iterator[None]:
    """Own ``robot``'s motion while a measurement is taken (unless the routine owns it already).

    A frame, and the robot pose read with it, measure something only while the robot stands
    still: refused with ``RobotBusy`` while another caller moves the robot. The robot is held
    with a still session (``MotionOwner.begin(still=True)``: nothing moves it meanwhile; a latched
    robot may be held). Once held, nothing of ours moves it; a robot that still reports moving
    after ``STILL_WAIT_S`` (a halt slowing down, or the teach pendant) is refused too.
    """
    if robot is None:
        yield
        return
    owned = ctx.motion is not None and robot.motion.holds(ctx.motion)
    session = None if owned else robot.motion.begin(ctx.started_by, f"routine {what}", still=True)
    try:
        deadline = time.monotonic() + STILL_WAIT_S
        while robot.state().moving:  # a halt or an arrival still settling
            if time.monotonic() > deadline:
                raise RobotBusy(f"robot {robot.robot_id} is moving (not by cellctl); {what} measures only while "
                                "it stands still — stop it, then try again")
            time.sleep(0.02)
        yield
    finally:
        if session is not None:
            robot.motion.end(session)


def capture(cam: Camera, robot: Robot | None, target: Target, name: str,
            ctx: JobContext | None = None) -> Capture:
    """One frame, the robot pose at the time of it, and the target detected in it.

    With ``ctx`` (every routine passes its own), the robot is held still for the shot
    (``robot_still``); without, the caller owns the robot or needs no pose.
    """
    with robot_still(ctx, robot, f"{ctx.name}: shot {name}") if ctx is not None else contextlib.nullcontext():
        T = robot.state().T_base_tool if robot is not None else None
        frame = cam.grab(timeout_s=5.0)
    det = detect(frame.pixels, target, name)
    return Capture(frame, det, T)


def approximate_camera(width: int, height: int) -> CameraModel:
    """A rough pinhole (f ~ 1.1 x width, a 50-degree lens) for planning before any calibration."""
    f = 1.1 * width
    return CameraModel("opencv5", width, height,
                       np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]]), np.zeros(5))


def detected_points_m(target: Target, det: Detection) -> NDArray[np.float64]:
    """(N, 3) target-frame points (m) of the detection's ids, in the detection's order."""
    pts = target.points()
    lookup = {int(i): k for k, i in enumerate(pts.ids)}
    return np.array([pts.xyz_m[lookup[int(i)]] for i in det.ids])


def target_pose(camera: CameraModel, target: Target, det: Detection) -> Mat4:
    return estimate_pose(camera, detected_points_m(target, det), det.uv).T_cam_target


def plan_pivot_stations(T0: Mat4, pivot_base_m: NDArray[np.float64], n: int, max_tilt_deg: float,
                        max_spin_deg: float, corner_shifts_m: list[tuple[float, float]] | None = None
                        ) -> list[Mat4]:
    """Tool poses around ``T0`` that keep looking at ``pivot_base_m`` (the plate's centre).

    Every other station is first shifted along the tool's x and y by one of ``corner_shifts_m``
    in turn (see ``corner_shifts_m``), which moves the plate towards an image corner; then each
    station rotates about the pivot — tilts up to ``max_tilt_deg`` in evenly spread directions
    (less for shifted stations), spins about the view axis up to ``max_spin_deg``. A rotation
    about the pivot keeps the plate where it was in the image. The first station is ``T0``.
    """
    pivot = np.asarray(pivot_base_m, dtype=np.float64)
    out = [T0.copy()]
    golden = math.pi * (3 - math.sqrt(5))
    shifts = corner_shifts_m or [(0.0, 0.0)]
    for k in range(1, n):
        az = k * golden
        tilt = math.radians(max_tilt_deg) * (0.45 + 0.55 * ((k * 0.618) % 1.0))
        start = T0.copy()
        if k % 2 == 1:
            tilt *= 0.5  # shifted stations: the plate is near an image corner, keep it in view
            dx, dy = shifts[(k // 2) % len(shifts)]
            start[:3, 3] += T0[:3, 0] * dx + T0[:3, 1] * dy
        axis_tool = np.array([math.cos(az), math.sin(az), 0.0])
        spin = math.radians(max_spin_deg) * math.sin(1.7 * k)
        view_axis = pivot - start[:3, 3]
        view_axis /= np.linalg.norm(view_axis)
        R = g.rotvec_to_matrix(T0[:3, :3] @ axis_tool * tilt) @ g.rotvec_to_matrix(view_axis * spin)
        T = np.eye(4)
        T[:3, :3] = R @ start[:3, :3]
        T[:3, 3] = pivot + R @ (start[:3, 3] - pivot)
        out.append(T)
    return out


def pivot_point(T_base_tool: Mat4, T_cam_target: Mat4, target: Target) -> NDArray[np.float64]:
    """The plate centre in the base frame, taking the camera frame as the tool's (a planning guess)."""
    centre_target = target.points().xyz_m.mean(axis=0)
    centre_cam = T_cam_target[:3, :3] @ centre_target + T_cam_target[:3, 3]
    return np.asarray(T_base_tool[:3, :3] @ centre_cam + T_base_tool[:3, 3], dtype=np.float64)


def corner_shifts_m(camera: CameraModel, distance_m: float, target: Target, det: Detection
                    ) -> list[tuple[float, float]]:
    """Camera shifts (m, along camera x and y, taken as the tool's) that bring the plate, now seen
    around the centroid of ``det``, near each of the four image corners while keeping it in view."""
    extent = getattr(target, "extent_m", None)
    x0, y0, x1, y1 = extent() if extent is not None else (0.0, 0.0, 0.0, 0.0)
    half_px = 0.5 * max(x1 - x0, y1 - y0) * camera.fx / distance_m
    u_c, v_c = det.uv.mean(axis=0)
    out = []
    for cx, cy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        u = camera.width / 2 + cx * max(camera.width / 2 - half_px, 0.0)
        v = camera.height / 2 + cy * max(camera.height / 2 - half_px, 0.0)
        # Moving the camera by +x moves the scene by -u in the image.
        out.append((-(u - u_c) * distance_m / camera.fx, -(v - v_c) * distance_m / camera.fy))
    return out


def reachable(robot: Robot, poses: list[Mat4]) -> tuple[list[Mat4], int]:
    ok = []
    for T in poses:
        try:
            robot.limits.check_pose(T)
        except MotionRejected:
            continue
        ok.append(T)
    return ok, len(poses) - len(ok)


def move(services: Services, ctx: JobContext, robot: RobotBase, T: Mat4, speed_m_s: float, why: str) -> None:
    """A checked linear move in the routine's motion session, audited under the job's caller."""
    ctx.check_cancelled()
    ctx.moved = True
    audited_move(services.store, ctx.started_by, robot, T, speed_m_s, why, ctx.motion)


def stop_robot_on_end(ctx: JobContext, robot: RobotBase | None) -> None:
    """Halt the robot when the routine ends, whatever the outcome (no latch: that is Stop's)."""
    if robot is not None:
        ctx.on_end.append(robot.halt)


def detection_inputs(caps: list[Capture]) -> list[dict[str, Any]]:
    """What a calibration stores as its inputs: each view's detection and robot pose."""
    out = []
    for c in caps:
        d = c.detection.to_json()
        if c.T_base_tool is not None:
            d["T_base_tool"] = np.asarray(c.T_base_tool).tolist()
        d["timestamp_s"] = c.frame.timestamp_s
        out.append(d)
    return out
