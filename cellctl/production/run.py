"""The production run: pick from the area, place into the next slot, cycle after cycle, until done.

One run per robot; it owns the robot's motion session for its whole life (a second mover gets
``RobotBusy``). Each cycle decides from a fresh picture: nothing found ends the run
``area_empty`` when the picture shows no object either, ``not_recognized`` when it does (parts the
model does not match: ``cellctl.production.occupancy``); parts found but none pickable (every pose
outside the envelope or the tool's cone, or every part skipped after its grip failed ``retries``
times) ends it ``none_pickable``. A failed
grip retreats empty and the part is tried again from a fresh picture.

States: ``running`` -> ``pausing`` (pause asked: the cycle finishes) -> ``paused`` -> ``running``;
``stopping`` (stop asked: the cycle finishes) -> ``stopped``; ``complete`` (count reached, area
empty, none pickable); ``failed`` (an error: the robot is halted). A robot Stop aborts the motion
session at once: the run ends ``stopped`` and the gripper is not opened (a held part stays held).
The control from other threads and the states: ``run_control``.

Exactly once (docs/production.md): the slot is claimed before the part is carried there and
confirmed once the gripper has let it go (``cellctl.production.slots``). The run's phase is stored
as it goes (``progress``), so that a run the service did not end is ended ``interrupted`` with where
it was at the next start (``cellctl.production.interrupted``). Cycle records: ``recorder``.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from calibration import geometry as g
from cellctl.mapping import ActiveMapping, active_mapping
from cellctl.motion import audited_move, halt_after_failure
from cellctl.pick.candidate import PickCandidate
from cellctl.pick.recipe import PickError
from cellctl.production.choice import Choice
from cellctl.production.config import LocatedPlace
from cellctl.production.frames import FailureFrames
from cellctl.production.gripper import Gripper
from cellctl.production.occupancy import not_recognized_detail
from cellctl.production.place import place_poses
from cellctl.production.recorder import CycleLog
from cellctl.production.records import Durations, clean, seen_fields
from cellctl.production.run_control import RunControl
from cellctl.production.slots import FixtureNotFound, SlotClaims
from cellctl.production.status import Ended, Phase, RunSettings, RunStatus, State
from cellctl.production.vision import (
    Picture,
    Prefetch,
    VisionWorker,
    camera_on_arm,
    next_picture,
    take_picture,
    tool_yaw,
)
from cellctl.production.writer import Writer
from cellctl.services import Services
from cellctl.store import Store
from drivers.base import MotionSession, RobotBase, RobotStopped

log = logging.getLogger(__name__)

VIEW_MARGIN_MM = 60.0
"""The arm counts as out of a fixed camera's view when nothing within this of its tool centre (the
gripper and the part it holds) is in the image."""
SEARCH_RETRIES = 2
"""A search that timed out with nothing found is repeated this many times before the run fails."""
__all__ = ["Ended", "Phase", "ProductionRun", "RunSettings", "RunStatus", "State"]


class ProductionRun(RunControl):
    """One run in its own thread (``start``); ``pause``/``resume``/``stop`` are safe from any thread
    (:class:`~cellctl.production.run_control.RunControl`)."""

    def __init__(self, services: Services, store: Store, settings: RunSettings, robot: RobotBase,
                 session: MotionSession, run_id: int, failure_frames: FailureFrames | None = None) -> None:
        self.services, self.store, self.s, self.robot, self.session = services, store, settings, robot, session
        self.failure_frames = failure_frames
        """Where the frames of failed cycles are kept (None: they are not kept beyond the frame cache)."""
        super().__init__(RunStatus(run_id, settings.recipe_id, settings.robot_id))
        self.gripper = Gripper(services, settings.recipe.gripper)
        device = settings.recipe.gripper.device
        self._choice = Choice(device.retries if device is not None else 0)
        self.slots = SlotClaims(store, settings.recipe_id, run_id)
        self.phase: Phase = "starting"
        self._cycle: tuple[PickCandidate, Picture, np.ndarray] | None = None
        self._mapping: ActiveMapping | None = None
        if settings.overlap and (isinstance(settings.recipe.place, LocatedPlace) or camera_on_arm(
                services, settings.camera_id, settings.robot_id, settings.recipe)):
            # A camera on the arm sees from the capture pose only, and a located place is in the camera's
            # view (the arm over it hides it): the picture is part of the cycle.
            settings.overlap = False
        if settings.overlap:
            mapping = active_mapping(services, settings.camera_id, settings.robot_id, settings.recipe.calibration,
                                     settings.recipe.plane_z_mm is not None)
            self._mapping = mapping if (mapping.kind == "handeye" and mapping.calib.get("setup") == "eye-to-hand"
                                        ) else None
        self._thread = threading.Thread(target=self._main, name=f"production-{run_id}", daemon=True)
        self.done = threading.Event()
        self._vision: VisionWorker | None = None
        """The next cycle's pictures (with ``overlap``): made when the run's thread starts, closed when it ends."""
        # Last: a run that fails to be made leaves no thread behind (the writer's thread starts here).
        self._writer = Writer(f"production-{run_id}-store")
        self.cycles = CycleLog(services, store, self._writer, run_id, settings.recipe_id, settings.recipe_version,
                               failure_frames)
        self._record = self.cycles.record

    # -- the run ----------------------------------------------------------------------------------
    def _main(self) -> None:
        try:
            if self.s.overlap:
                self._vision = VisionWorker(f"production-{self.status.run_id}-vision")
            ended = self._cycles()
            self._go_home()
            state: State = "stopped" if ended == "stopped" else "complete"
            self._end(state, ended)
        except RobotStopped as exc:
            # The emergency path (or the service's shutdown): halted already; the gripper keeps what it holds.
            self.status.stop_reason = self._abort_reason or str(exc)
            slot = self._settle_claim(self.status.stop_reason)
            self._record("stopped", detail=self.status.stop_reason, **{"phase": self.phase, **slot})
            self._end("stopped", "stopped", None)
        except Exception as exc:  # noqa: BLE001 - the run ends failed, saying why; the robot is halted
            log.exception("production run %s failed", self.status.run_id)
            halt_after_failure(self.robot, exc)
            self._settle_claim(f"the run failed: {exc}")
            self._end("failed", "failed", str(exc))
        finally:
            if self._vision is not None:
                self._vision.close()  # a picture in progress finishes (bounded by its grab and search time-outs)
            self._writer.flush()
            self._writer.close()
            self.robot.motion.end(self.session)
            self.done.set()

    def _cycles(self) -> Ended:
        self._move_to_capture()
        prefetch: Prefetch | None = None
        while True:
            ended = self._between_cycles()
            if ended is not None:
                return ended
            t_cycle = time.monotonic()
            d = Durations()
            if prefetch is not None:
                picture, waited = prefetch.wait()
                prefetch = None
            else:
                self._move_to_capture()
                picture = self._picture()
                waited = picture.took_s
            for _ in range(SEARCH_RETRIES):
                if picture.candidates or not picture.timed_out:
                    break
                # Nothing found in a search that ran out of time is not an empty area: look again.
                log.warning("production run %s: the search timed out with nothing found; looking again",
                            self.status.run_id)
                picture = self._picture()
                waited += picture.took_s
            d.add("vision", waited)
            self._drift(picture)
            self.session.check()
            if not picture.candidates and picture.timed_out:
                why = (f"the search ran out of its time ({self.s.recipe.search.timeout_s} s) {SEARCH_RETRIES + 1} "
                       "times with nothing found: raise the recipe's search.timeout_s")
                self._record("vision_failed", picture=picture, detail=why)
                raise PickError(why)
            if not picture.candidates and picture.occupancy is not None and picture.occupancy.occupied:
                # Nothing matched, yet the picture shows objects: parts the model does not recognise, not an
                # empty area (cellctl.production.occupancy); a refill call would be wrong.
                why = not_recognized_detail(picture.occupancy, picture.reason)
                self._record("not_recognized", picture=picture, detail=why)
                return "not_recognized"
            if not picture.candidates:
                self.status.counters.empty_area += 1
                self._record("empty", picture=picture, detail=picture.reason or "nothing found")
                return "area_empty"
            cand = self._choice.choose(picture, self.status.counters)
            if cand is None:
                self._record("none_pickable", picture=picture, detail=self._choice.why_none(picture))
                return "none_pickable"
            prefetch = self._pick_and_place(cand, picture, d, t_cycle)

    def _at(self, phase: Phase, store: bool = False, **info: Any) -> None:
        """The run is now at ``phase`` of cycle ``_n + 1``; ``store``: write it (in order, off the cycle's path)."""
        self.phase = phase
        if store:
            progress = clean({"phase": phase, "n": self._n + 1, "slot": self.slots.claim, "at_s": time.time(), **info})
            run_id = self.status.run_id
            self._writer.put(lambda: self.store.set_progress(run_id, progress))

    def _settle_claim(self, why: str) -> dict[str, Any]:
        """The run ends with a slot claimed: placed or in doubt (``SlotClaims.settle``)."""
        pick_pose = None if self._cycle is None else seen_fields(self._cycle[0], None, None)["pick_pose"]
        return self.slots.settle(why, self.phase, self._holding, pick_pose, self._placed)

    def _holding(self) -> bool | None:
        try:
            return self.gripper.holding()
        except Exception:  # noqa: BLE001 - unknown: said so
            return None

    def _placed(self, slot: int, detail: str = "") -> None:
        """Count and record the cycle whose part was let go in ``slot``."""
        self.status.counters.placed += 1
        if self._cycle is None:
            self._record("placed", slot=slot, detail=detail, resolves=slot)
            return
        cand, picture, T_place = self._cycle
        self._record("placed", cand, picture, slot=slot, T_place=T_place, detail=detail, resolves=slot)

    # -- one cycle --------------------------------------------------------------------------------
    def _move(self, T: np.ndarray, why: str, d: Durations) -> None:
        """The audited move (``cellctl.motion``), its audit row written by the run's writer thread."""
        t0 = time.monotonic()
        try:
            audited_move(self.services.store, self.s.who, self.robot, T, self.s.recipe.speed_m_s,
                         f"production run {self.status.run_id}: {why}", self.session, write=self._writer.put)
        finally:
            d.add("motion", time.monotonic() - t0)

    def _go_home(self) -> None:
        """A run that ends by itself or by an operator's stop leaves the arm at the robot's ``home`` named
        pose (``robots.<id>.poses.home``), not hovering over the last slot; none named: it stays."""
        robot_config = self.services.config.robots.get(self.s.robot_id)
        home = None if robot_config is None else robot_config.poses.get("home")
        if home is None:
            return
        self._move(g.ur_pose_to_transform(list(home)), "home at the end of the run", Durations())

    def _move_to_capture(self) -> None:
        r = self.s.recipe
        if r.capture_pose_ur is None:
            return
        T = g.ur_pose_to_transform(list(r.capture_pose_ur))
        here = self.robot.state().T_base_tool
        if float(np.linalg.norm(here[:3, 3] - T[:3, 3])) > 1e-3:
            self._move(T, "to the capture pose", Durations())

    def _drift(self, picture: Picture) -> None:
        """Every ``drift.every_cycles``-th picture is a drift check too, on the run's store thread (no extra
        picture or motion); an alarm with ``drift.pause_on_alarm`` pauses the run after this cycle."""
        drift = self.services.drift
        if drift is not None:
            drift.on_production_picture(self, picture.frame_id, self.s.camera_id, self._writer.put)

    def _picture(self) -> Picture:
        yaw = tool_yaw(self.robot.state().T_base_tool)
        return take_picture(self.services, self.s.recipe_id, self.s.recipe_version, self.s.recipe, self.s.camera_id,
                            self.robot, yaw)

    def _pick_and_place(self, cand: PickCandidate, picture: Picture, d: Durations, t_cycle: float
                        ) -> Prefetch | None:
        r, c = self.s.recipe, self.status.counters
        # The place is checked before the pick: a full pattern or a refused place pose ends the run
        # with the part where it lies, not in the gripper.
        try:
            slot, n_slots, T_slot = self.slots.target(r, picture.T_base_fixture, picture.fixture)
        except FixtureNotFound as exc:
            self._record("vision_failed", cand, picture, detail=str(exc))
            raise PickError(f"{exc}; the part is left where it lies") from exc
        T_place, T_place_app = place_poses(r, cand, T_slot, self.robot.limits)
        self._cycle = (cand, picture, T_place)
        self._at("to_pick", store=True, pick_pose=seen_fields(cand, None, None)["pick_pose"])
        d.add("gripper", self.gripper.open())
        self._move(cand.T_approach, "pre-pick", d)
        self._move(cand.T_pick, "pick", d)
        self._at("closing")
        check = self.gripper.close_and_check()
        d.add("gripper", check.elapsed_s)
        self._at("lifting")
        self._move(cand.T_approach, "post-pick", d)
        if not check.held:
            c.grip_failures += 1
            failures = self._choice.grip_failed(cand)
            if failures > self._choice.retries:
                c.skipped += 1
                self._record("skipped", cand, picture, d=d, detail=f"{check.detail}; skipped after "
                             f"{failures} failed grips", t_cycle=t_cycle)
            else:
                c.retries += 1
                self._record("grip_failed", cand, picture, d=d, detail=check.detail, t_cycle=t_cycle)
            return None
        c.picked += 1
        self.slots.take(slot, n_slots, self._n + 1, {"pick_pose": seen_fields(cand, None, None)["pick_pose"],
                                                     "place_pose": seen_fields(None, None, T_place)["place_pose"]})
        self._at("carrying", store=True, holding=True)
        prefetch = self._next_picture(T_place)
        try:
            self._move(T_place_app, "pre-place", d)
        except BaseException:
            if prefetch is not None:
                prefetch.cancel()
            raise
        if prefetch is not None:
            prefetch.go()  # at the latest now: the arm is over the place, out of the camera's view
        claimed = self._put_down(T_place, T_place_app, d)
        c.placed += 1
        durations = d.as_ms(time.monotonic() - t_cycle)
        self.status.times.add(durations)
        self._record("placed", cand, picture, slot=slot, T_place=T_place, d=d, t_cycle=t_cycle,
                     durations=durations, resolves=claimed)
        return prefetch

    def _put_down(self, T_place: np.ndarray, T_place_app: np.ndarray, d: Durations) -> int | None:
        """From over the slot: down, release, away, each phase stored as it begins; the slot's claim
        resolved once the arm has left (by the placed record, in one transaction). The one place step of
        every run (still area and belt), so exactly-once placement holds for both."""
        self._at("over_slot")
        self._move(T_place, "place", d)
        self._at("releasing")
        d.add("gripper", self.gripper.release())
        self.slots.released = True
        self._at("leaving", store=True, holding=False)
        self._move(T_place_app, "post-place", d)
        claimed = self.slots.resolve()
        self._at("between")
        return claimed

    def _next_picture(self, T_place: np.ndarray) -> Prefetch | None:
        """With ``overlap``, the next cycle's picture on the vision thread (``vision.next_picture``)."""
        s = self.s

        def take() -> Picture:
            return take_picture(self.services, s.recipe_id, s.recipe_version, s.recipe, s.camera_id, self.robot,
                                tool_yaw(T_place))

        return next_picture(self._vision, take, self._mapping, self.robot, VIEW_MARGIN_MM)
