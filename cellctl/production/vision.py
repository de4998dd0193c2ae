"""A production cycle's picture: grab, search the recipe's parts, plan each one's pick.

With a fixed camera the picture of the next cycle is taken and searched while the robot places
the current part (``Prefetch``: a thread), so that the cycle waits for vision only when the search
takes longer than the place. With a camera on the arm the capture pose is part of the cycle.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration import geometry as g
from cellctl.arm_view import arm_view
from cellctl.mapping import ActiveMapping, active_mapping
from cellctl.pick.flow import _locate
from cellctl.pick.place import LocatedPlace
from cellctl.pick.recipe import Recipe
from cellctl.production.fixture import locate_fixture, slots_in_base
from cellctl.production.occupancy import Occupancy, occupancy, part_sides_px
from cellctl.production.place import Plan, plan_part
from cellctl.services import Services
from drivers.base import RobotBase

IN_SLOT_MM = 8.0
"""A part found this close to a located place's slot lies in it (placed): it is not a candidate."""


@dataclass
class Candidate:
    """One found part: the match as the pick answer gives it, and its plan."""

    match: dict[str, Any]
    plan: Plan


@dataclass
class Picture:
    """What one capture found: the candidates (best score first), the frame and the time it took."""

    candidates: list[Candidate]
    frame_id: int | None
    reason: str | None
    calibration: dict[str, Any]
    took_s: float
    found: int = 0
    timed_out: bool = False
    """The search ran out of its time budget (``search.timeout_s``): what it found may not be all."""
    extra: dict[str, Any] = field(default_factory=dict)
    T_base_fixture: Any = None
    """A located place: the fixture found in this picture (4x4, metres); None when not found or not located."""
    fixture: dict[str, Any] | None = None
    """A located place: the fixture's match (score, pixels) or why it was not found."""
    arm: str | None = None
    """What of the arm the picture showed in the search region (its matches there were dropped); None: none."""
    occupancy: Occupancy | None = None
    """With no candidate: the objects the picture shows anyway (``cellctl.production.occupancy``)."""


def camera_on_arm(services: Services, camera_id: str, robot_id: str, recipe: Recipe) -> bool:
    """True when the active calibration says the camera rides on the arm (eye-in-hand)."""
    return active_mapping(services, camera_id, robot_id, recipe.calibration,
                          recipe.plane_z_mm is not None).camera_on_arm


def take_picture(services: Services, recipe_id: int, version: int, recipe: Recipe, camera_id: str,
                 robot: RobotBase, current_yaw: float) -> Picture:
    """Grab and search now; plan every match (pick poses checked against the robot's limits)."""
    t0 = time.monotonic()
    answer = _locate(services, recipe_id, version, recipe, camera_id, robot)
    mapping = active_mapping(services, camera_id, robot.robot_id, recipe.calibration, recipe.plane_z_mm is not None)
    T_capture = np.array(robot.state().T_base_tool) if mapping.kind == "handeye" else None
    cands = []
    for m in sorted(answer["picks"], key=lambda p: -float(p["score"])):
        cands.append(Candidate(m, plan_part(mapping, recipe, m, T_capture, current_yaw, robot.limits)))
    cands, arm, occupied = _what_it_sees(services, answer, mapping, recipe, cands)
    T_fixture, fixture = None, None
    if isinstance(recipe.place, LocatedPlace) and answer.get("frame_id") is not None:
        # The fixture in the same frame; the parts already in its slots are placed, not to be picked.
        pixels = services.frames.get(int(answer["frame_id"])).pixels
        T_fixture, fixture = locate_fixture(recipe.place, pixels, mapping, T_capture)
        if T_fixture is not None:
            slots = [T[:2, 3] * 1e3 for T in slots_in_base(recipe.place, T_fixture)]
            cands = [c for c in cands if min(float(np.linalg.norm(c.plan.T_base_part[:2, 3] * 1e3 - xy))
                                             for xy in slots) >= IN_SLOT_MM]
    device = recipe.gripper.device
    if device is not None and device.clearance_mm is not None:
        _neighbours(cands, device.clearance_mm)
    return Picture(cands, answer.get("frame_id"), answer.get("reason"), answer.get("calibration") or {},
                   time.monotonic() - t0, len(cands), bool(answer.get("timed_out")), T_base_fixture=T_fixture,
                   fixture=fixture, arm=arm, occupancy=occupied)


def _what_it_sees(services: Services, answer: dict[str, Any], mapping: ActiveMapping, recipe: Recipe,
                  cands: list[Candidate]) -> tuple[list[Candidate], str | None, Occupancy | None]:
    """The candidates outside the arm's region (a fixed camera: ``cellctl.arm_view``, at the pose the picture
    was taken at), what of the arm was in view, and, when no candidate is left, whether the picture still
    shows objects (``cellctl.production.occupancy``)."""
    pose = answer.get("capture_pose") or {}
    arm = None
    if pose and answer.get("frame_id") is not None:
        T = g.ur_pose_to_transform([pose["x_mm"] * 1e-3, pose["y_mm"] * 1e-3, pose["z_mm"] * 1e-3,
                                    pose["rx_rad"], pose["ry_rad"], pose["rz_rad"]])
        arm = arm_view(mapping, T, services.config)
    if arm is not None:
        cands = [c for c in cands if not arm.covers(float(c.match["u_px"]), float(c.match["v_px"]))]
    occupied = None
    if not cands and answer.get("frame_id") is not None:
        pixels = services.frames.get(int(answer["frame_id"])).pixels
        occupied = occupancy(pixels, recipe.search.roi, part_sides_px(recipe.models),
                             arm.mask if arm is not None else None)
    return cands, (arm.what if arm is not None and arm.share_of(recipe.search.roi) > 0 else None), occupied


def _neighbours(cands: list[Candidate], clearance_mm: float) -> None:
    """Mark the parts the gripper would hit a neighbour at (reference points nearer than ``clearance_mm``)."""
    xy = [c.plan.T_base_part[:2, 3] * 1e3 for c in cands]
    for i, c in enumerate(cands):
        if c.plan.problem is not None:
            continue
        near = [float(np.linalg.norm(xy[i] - xy[j])) for j in range(len(cands)) if j != i]
        if near and min(near) < clearance_mm:
            c.plan.problem = (f"a neighbour lies {min(near):.1f} mm from it (clearance {clearance_mm:g} mm): "
                              "the gripper would hit it")


def out_of_view(mapping: ActiveMapping, T_base_tool: Any, margin_mm: float) -> bool:
    """True when nothing within ``margin_mm`` of the tool centre (the gripper and the part it holds)
    can be in the fixed camera's image: a disc of points around it, at its height, all project
    outside the image (through the active eye-to-hand calibration)."""
    cam = mapping.camera
    if mapping.kind != "handeye" or mapping.calib.get("setup") != "eye-to-hand" or cam is None:
        return False
    T_cam_base = g.invert(np.asarray(mapping.calib["T_base_cam"], dtype=np.float64))
    p = np.asarray(T_base_tool, dtype=np.float64)[:3, 3]
    a = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)
    ring = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)]) * margin_mm * 1e-3
    pts = np.concatenate([p + ring, p + ring * 0.5, [p]])
    uv = cam.project(g.transform_points(T_cam_base, pts))
    inside = (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5)
              & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5))
    return not bool(inside.any())


class ViewWatch:
    """Starts the next picture as soon as the arm is out of the fixed camera's view (polls the robot)."""

    def __init__(self, start: Callable[[], Prefetch], robot: RobotBase, mapping: ActiveMapping,
                 margin_mm: float, poll_s: float = 0.01) -> None:
        self.prefetch: Prefetch | None = None
        self._stop = threading.Event()

        def watch() -> None:
            while not self._stop.is_set():
                try:
                    if out_of_view(mapping, robot.state().T_base_tool, margin_mm):
                        self.prefetch = start()
                        return
                except Exception:  # noqa: BLE001 - no early picture; the cycle takes it after the move
                    return
                self._stop.wait(poll_s)

        self._thread = threading.Thread(target=watch, name="production-view-watch", daemon=True)
        self._thread.start()

    def stop(self) -> Prefetch | None:
        """Stop watching; the picture started meanwhile, if any."""
        self._stop.set()
        self._thread.join(5.0)
        return self.prefetch


class Prefetch:
    """A picture taken and searched in the background (the robot is out of the camera's view)."""

    def __init__(self, services: Services, recipe_id: int, version: int, recipe: Recipe, camera_id: str,
                 robot: RobotBase, current_yaw: float) -> None:
        self.future: Future[Picture] = Future()

        def work() -> None:
            try:
                self.future.set_result(take_picture(services, recipe_id, version, recipe, camera_id, robot,
                                                    current_yaw))
            except BaseException as exc:  # noqa: BLE001 - handed to the cycle that waits for it
                self.future.set_exception(exc)

        threading.Thread(target=work, name="production-vision", daemon=True).start()

    def wait(self) -> tuple[Picture, float]:
        """The picture and the seconds the caller waited for it."""
        t0 = time.monotonic()
        picture = self.future.result()
        return picture, time.monotonic() - t0


def tool_yaw(T: Any) -> float:
    return math.atan2(float(T[1][0]), float(T[0][0]))
