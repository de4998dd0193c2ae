"""A production cycle's picture: grab, search the recipe's parts, one ``PickCandidate`` each.

The candidates come from the pick's one path (``cellctl.pick.candidate.locate``): the match, the
part's pose, the grasp, reachable or not, computed once. With a fixed camera the picture of the next
cycle is taken and searched while the robot places the current part, on the run's one vision
thread (``VisionWorker``: started with the run, joined when it ends), as soon as the arm is out of
the camera's view, so that the cycle waits for vision only when the search takes longer than the
place. With a camera on the arm the capture pose is part of the cycle.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration import geometry as g
from cellctl.mapping import ActiveMapping, active_mapping
from cellctl.pick.candidate import PickCandidate, locate
from cellctl.pick.recipe import Recipe
from cellctl.production.config import LocatedPlace
from cellctl.production.fixture import slots_in_base
from cellctl.production.occupancy import Occupancy, model_radius_px, occupancy, part_sides_px
from cellctl.services import Services
from drivers.base import RobotBase

log = logging.getLogger(__name__)

IN_SLOT_MM = 8.0
"""A part found this close to a located place's slot lies in it (placed): it is not a candidate."""
WORKER_JOIN_S = 60.0
"""At the run's end the vision thread finishes the picture it is taking (a grab and a search, both
bounded by their time-outs) within this, else it is logged."""


@dataclass
class Picture:
    """What one capture found: the candidates (best score first), the frame and the time it took."""

    candidates: list[PickCandidate]
    frame_id: int | None
    reason: str | None
    calibration: dict[str, Any]
    took_s: float
    found: int = 0
    timed_out: bool = False
    """The search ran out of its time budget (``search.timeout_s``): what it found may not be all."""
    T_base_fixture: Any = None
    """A located place: the fixture found in this picture (4x4, metres); None when not found or not located."""
    fixture: dict[str, Any] | None = None
    """A located place: the fixture's match (score, pixels) or why it was not found."""
    arm: str | None = None
    """What of the arm the picture showed in the search region (its matches there were dropped); None: none."""
    occupancy: Occupancy | None = None
    """With no candidate: the objects the picture shows anyway (``cellctl.production.occupancy``)."""
    encoder_ticks: int | None = None
    """A belt's encoder count at the exposure (conveyor tracking); None: no belt."""


def camera_on_arm(services: Services, camera_id: str, robot_id: str, recipe: Recipe) -> bool:
    """True when the active calibration says the camera rides on the arm (eye-in-hand)."""
    return active_mapping(services, camera_id, robot_id, recipe.calibration,
                          recipe.plane_z_mm is not None).camera_on_arm


def take_picture(services: Services, recipe_id: int, version: int, recipe: Recipe, camera_id: str,
                 robot: RobotBase, current_yaw: float) -> Picture:
    """Grab and search now: every match a candidate (pick poses checked against the robot's limits,
    the grasp folded nearest ``current_yaw``, radians)."""
    t0 = time.monotonic()
    # A located place's fixture is found in the same frame, in the same visit (cellctl.pick.fixture).
    place = recipe.place if isinstance(recipe.place, LocatedPlace) else None
    located = locate(services, recipe_id, version, recipe, camera_id, robot, near_yaw=current_yaw, fixture=place)
    cands = sorted(located.candidates, key=lambda c: -float(c.match.score))
    T_fixture, fixture = located.T_base_fixture, located.fixture
    if place is not None and T_fixture is not None:
        # The parts already in the fixture's slots are placed, not to be picked.
        slots = [T[:2, 3] * 1e3 for T in slots_in_base(place, T_fixture)]
        cands = [c for c in cands if min(float(np.linalg.norm(c.T_base_part[:2, 3] * 1e3 - xy))
                                         for xy in slots) >= IN_SLOT_MM]
    device = recipe.gripper.device
    if device is not None and device.clearance_mm is not None:
        _neighbours(cands, device.clearance_mm)
    occupied = None
    if not cands:
        # Nothing to pick: does the picture show objects anyway (parts nothing matched), or is the area empty?
        arm = located.arm
        r_part = max((model_radius_px(m) for m in recipe.models), default=0.0)
        known = [(float(c.match.u_px), float(c.match.v_px), r_part) for c in located.candidates]
        if isinstance(recipe.place, LocatedPlace) and fixture is not None and "u_px" in fixture:
            known.append((float(fixture["u_px"]), float(fixture["v_px"]), model_radius_px(recipe.place.model)))
        occupied = occupancy(services.frames.get(located.frame_id).pixels, recipe.search.roi,
                             part_sides_px(recipe.models), arm.mask if arm is not None else None, known)
    return Picture(cands, located.frame_id, located.reason, located.calibration, time.monotonic() - t0, len(cands),
                   located.timed_out, T_base_fixture=T_fixture, fixture=fixture, arm=located.arm_in_view,
                   occupancy=occupied,
                   encoder_ticks=located.encoder_ticks)


def _neighbours(cands: list[PickCandidate], clearance_mm: float) -> None:
    """Mark the parts the gripper would hit a neighbour at (reference points nearer than ``clearance_mm``)."""
    xy = [c.T_base_part[:2, 3] * 1e3 for c in cands]
    for i, c in enumerate(cands):
        if c.problem is not None:
            continue
        near = [float(np.linalg.norm(xy[i] - xy[j])) for j in range(len(cands)) if j != i]
        if near and min(near) < clearance_mm:
            c.problem = (f"a neighbour lies {min(near):.1f} mm from it (clearance {clearance_mm:g} mm): "
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


class Prefetch:
    """The next cycle's picture, taken on the run's vision thread: ``wait`` for it. Until the thread
    starts it, it may wait for the arm to leave the camera's view (``go`` starts it at once)."""

    def __init__(self, take: Callable[[], Picture], ready: Callable[[], bool] | None, poll_s: float) -> None:
        self.future: Future[Picture] = Future()
        self._take = take
        self._ready = ready
        self._poll_s = poll_s
        self._go = threading.Event()
        self.early = False
        """The picture was started by the watch (the arm left the view), not by ``go``."""

    def go(self) -> None:
        """Take the picture now, whether or not the arm has left the view."""
        self._go.set()

    def cancel(self) -> None:
        """Not needed any more: not taken if not started yet (``wait`` would raise ``CancelledError``)."""
        self.future.cancel()
        self._go.set()

    def wait(self) -> tuple[Picture, float]:
        """The picture and the seconds the caller waited for it."""
        self.go()
        t0 = time.monotonic()
        picture = self.future.result()
        return picture, time.monotonic() - t0

    def _run(self) -> None:
        """On the vision thread: watch until the arm is out of view (or ``go``), then take the picture."""
        ready = self._ready
        while not self._go.is_set():
            if ready is None:
                self._go.wait()
                break
            try:
                if ready():
                    self.early = True
                    break
            except Exception:  # noqa: BLE001 - no early picture; the cycle starts it after the move
                ready = None
                continue
            self._go.wait(self._poll_s)
        if not self.future.set_running_or_notify_cancel():
            return
        try:
            self.future.set_result(self._take())
        except BaseException as exc:  # noqa: BLE001 - handed to the cycle that waits for it
            self.future.set_exception(exc)


class VisionWorker:
    """A run's one vision thread: takes the next pictures (``Prefetch``) in order, one at a time;
    ``close`` ends it and joins it (the run's end)."""

    def __init__(self, name: str) -> None:
        self._q: queue.Queue[Prefetch | None] = queue.Queue()
        self._current: Prefetch | None = None
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, take: Callable[[], Picture], ready: Callable[[], bool] | None = None,
               poll_s: float = 0.01, now: bool = False) -> Prefetch:
        """A picture to take: ``now``, or when ``ready()`` says so (polled every ``poll_s``), or at the
        handle's ``go``, whichever comes first."""
        job = Prefetch(take, ready, poll_s)
        if now:
            job.go()
        self._q.put(job)
        return job

    def _loop(self) -> None:
        while True:
            job = self._q.get()
            if job is None:
                return
            self._current = job
            job._run()
            self._current = None

    def close(self, timeout_s: float = WORKER_JOIN_S) -> None:
        """Cancel the pictures not started, let the one in progress finish, end the thread and join it."""
        while True:
            try:
                job = self._q.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                job.cancel()
        current = self._current
        if current is not None:
            current.cancel()  # a watch in progress ends untaken; a picture being taken finishes
        self._q.put(None)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.error("production: the vision thread %s did not end within %.0f s", self._thread.name, timeout_s)


def next_picture(worker: VisionWorker | None, take: Callable[[], Picture], mapping: ActiveMapping | None,
                 robot: RobotBase, margin_mm: float) -> Prefetch | None:
    """The next cycle's picture on ``worker`` (None: no overlap, no picture): with a fixed camera's
    eye-to-hand ``mapping`` it starts as soon as the arm has left the camera's view (nothing within
    ``margin_mm`` of the tool centre in the image), else when the handle's ``go`` is called."""
    if worker is None:
        return None
    if mapping is None:
        return worker.submit(take)
    m = mapping

    def out() -> bool:
        return out_of_view(m, robot.state().T_base_tool, margin_mm)

    return worker.submit(take, out)


def tool_yaw(T: Any) -> float:
    return math.atan2(float(T[1][0]), float(T[0][0]))
