"""A production run from a moving belt (a recipe's ``source: {kind: conveyor}``; docs/conveyor.md).

The belt does not stop. A vision thread takes pictures one after the other; each picture's matches
are mapped at the encoder count latched at its exposure and queued in the belt's frame
(``cellctl.production.belt``: the same part in several pictures is one). The run's thread takes the
part furthest along that the robot can still meet inside the window (``plan_meeting`` with the robot's own
timing of its moves, ``RobotBase.linear_move_s``, plus the lead the run measured on its own approaches; the
grasp folded to the one nearest the tool's yaw), moves above the meeting point while the gripper opens, waits
for the count at which the part is there (an arm there late plans the meeting again further along the
window, from where it is), then lets the robot track the belt (``RobotBase.start_tracking``:
commanded poses ride the belt) while it goes down, closes the gripper and comes up; then it stops
tracking and places the part as a still run does (the slot claimed first: exactly once). A part that
cannot be met before it leaves the window is given up, counted ``missed_window`` and recorded; the
robot never chases it out of the window.

Safety: every commanded pose is checked against the envelope by ``move_linear``; while tracking, the
pose is also checked where the belt can carry it (the controller's tracking limit is the window's
end). A robot Stop halts the arm and ends tracking at once (the held part stays held); the run ends
``stopped``. Faults end the run ``failed`` with the reason: a count that jumps (faster than any belt; the count
is watched every ``WATCH_S`` while the run runs, and a jump halts the arm at once, mid-move too),
an encoder that stopped while the parts moved (two pictures at one count, the parts elsewhere), a
belt that stopped with the robot waiting for a part (``belt_stopped`` is recorded; the part stays
queued and is met where it lies if that is in the window).

This module: the run's threads (the vision thread's pictures into the queue; the count watcher,
``BeltMeetingRun._watch_count``; the run's cycles) and a belt
cycle from the meeting to the place. The meeting (which part, the plan, the arm above the meeting point, the
wait, a later meeting): :class:`cellctl.production.belt_meeting.BeltMeetingRun`, its base.
"""

from __future__ import annotations

import functools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any

import numpy as np

from cellctl.pick.recipe import PickError
from cellctl.production.belt import BeltPart, Meeting
from cellctl.production.belt_meeting import GRIP_CLOSE_S, BeltMeetingRun
from cellctl.production.place import place_poses
from cellctl.production.records import Durations, seen_fields
from cellctl.production.status import Ended
from cellctl.production.vision import take_picture
from drivers.base import MotionRejected

CLAIM_WAIT_S = 30.0
"""The longest the arm waits over the place for the slot's claim to be stored, s."""
ENCODER_STOP_S = 0.3
"""Two pictures this far apart in time at one count, the parts elsewhere: the encoder stopped."""


class ConveyorRun(BeltMeetingRun):
    """A production run whose parts come on a belt (one per robot, like a still run)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """As :class:`~cellctl.production.belt_meeting.BeltMeetingRun` (``belt``, ``conveyor``, ``window_mm``)."""
        super().__init__(*args, **kwargs)
        self._fault: str | None = None
        """Why the vision thread ended the run (set there, raised on the run's thread)."""
        self._seen_s = time.monotonic()
        """When a picture last showed a part (monotonic s)."""
        self._cycles_over = threading.Event()
        """Set when the run's cycles end: its vision thread and count watcher stop."""
        self.pictures = 0
        """Pictures the vision thread took so far."""

    def public(self) -> dict[str, Any]:
        return {**super().public(), "conveyor": self._belt_state()}

    def snapshot(self) -> dict[str, Any]:
        return {**super().snapshot(), "queue_length": len(self.queue)}

    def _belt_state(self) -> dict[str, Any]:
        return {"conveyor_id": self.conveyor.conveyor_id, "queue_length": len(self.queue),
                "speed_mm_s": round(self.watch.speed_mm_s(), 1), "window_mm": list(self.window_mm),
                "pictures": self.pictures, "calibration_id": self.belt.calibration_id}

    # -- the vision thread -------------------------------------------------------------------------
    def _look(self) -> None:
        """Pictures one after the other until the run ends; each one's parts into the queue."""
        s = self.s
        last: tuple[float, int, int] | None = None  # (time, count, parts) of the previous picture
        while not self._cycles_over.is_set():
            try:
                picture = take_picture(self.services, s.recipe_id, s.recipe_version, s.recipe, s.camera_id,
                                       self.robot, 0.0)
            except Exception as exc:  # noqa: BLE001 - the run fails saying why
                self._fault = f"the camera or the search failed: {exc}"
                return
            self.pictures += 1
            self._drift(picture)  # every drift.every_cycles-th picture is a drift check (the run's store thread)
            if picture.encoder_ticks is None:
                self._fault = (f"camera {s.camera_id}'s frames carry no encoder count (Frame.meta['encoder_ticks']): "
                               "a belt run needs the count latched at each exposure (docs/conveyor.md)")
                return
            cands = [c for c in picture.candidates if c.problem is None or c.refused is not None]
            seen = self.queue.add(cands, picture.encoder_ticks, picture.frame_id, picture)
            now = time.monotonic()
            if cands:
                self._seen_s = now
            if (last is not None and abs(picture.encoder_ticks - last[1]) <= 1 and now - last[0] >= ENCODER_STOP_S
                    and last[2] > 0 and seen.added > 0 and seen.merged == 0 and seen.done == 0):
                self._fault = (f"the encoder count stood at {picture.encoder_ticks} for {now - last[0]:.1f} s while "
                               f"the parts moved on the belt ({seen.added} seen where none was expected): the "
                               "encoder stopped counting; check its coupling to the belt")
                return
            last = (now, picture.encoder_ticks, len(cands))

    # -- the run's thread -------------------------------------------------------------------------
    def _cycles(self) -> Ended:
        r = self.s.recipe
        if r.place is None or r.place.kind == "located":
            raise PickError("a belt run places into a fixed or grid place (a located place needs the arm out of "
                            "the place's picture: not on a belt)")
        self._go_home()
        run_id = self.status.run_id
        looker = threading.Thread(target=self._look, name=f"production-{run_id}-belt", daemon=True)
        watcher = threading.Thread(target=self._watch_count, args=(self._cycles_over,),
                                   name=f"production-{run_id}-count", daemon=True)
        looker.start()
        watcher.start()
        self._opener = ThreadPoolExecutor(1, thread_name_prefix=f"production-{run_id}-gripper")
        try:
            ended = self._belt_cycles()
        except Exception as exc:
            if self._count_fault is None:
                raise
            raise PickError(self._count_fault) from exc  # the watcher aborted the cycle (a move raised): its reason
        finally:
            self._cycles_over.set()
            self._opener.shutdown(wait=True)
            looker.join(30.0)
            watcher.join(30.0)
        if self._count_fault is not None:  # caught as the cycles ended
            raise PickError(self._count_fault)
        return ended

    def _belt_cycles(self) -> Ended:
        r = self.s.recipe
        if r.source is None:
            raise PickError("a belt run needs a recipe with source: {kind: conveyor}")
        just_cycled = True
        while True:
            if just_cycled or self._stop or self._pause or (self.s.count and
                                                            self.status.counters.placed >= self.s.count):
                ended = self._between_cycles()
                if ended is not None:
                    return ended
                just_cycled = False
            self.session.check()
            self._check_count()
            if self._fault is not None:
                raise PickError(self._fault)
            found = self._next_part()
            if found is None:
                if not self.s.count and time.monotonic() - self._seen_s > r.source.idle_timeout_s:
                    self.status.counters.empty_area += 1
                    self._record("empty", detail=f"the belt brought no part for {r.source.idle_timeout_s:g} s")
                    return "area_empty"
                time.sleep(0.01)
                continue
            self._pick_from_belt(*found)
            just_cycled = True

    def _pick_from_belt(self, part: BeltPart, meeting: Meeting) -> None:
        r, c, belt = self.s.recipe, self.status.counters, self.belt
        t_cycle, d = time.monotonic(), Durations()
        over: dict[str, float] = {}  # the cycle's time outside motion, gripper and the wait for the part, s
        cand, picture = part.cand, part.picture
        slot, n_slots, T_slot = self.slots.target(r, None, None)
        T_place, T_place_app = place_poses(r, cand, T_slot, self.robot.limits)
        over["setup"] = time.monotonic() - t_cycle
        self._at("to_pick", store=True, pick_pose=seen_fields(cand, None, None)["pick_pose"])
        met = self._meet(part, meeting, d, t_cycle)
        if met is None:
            return  # missed (recorded), or the belt stopped or slowed: the part stays queued and is planned again
        ticks, meeting, waited_ms, replans = met
        x_part = part.x_at(belt, ticks)
        most_m = (self.window_mm[1] - x_part) * 1e-3
        t0 = time.monotonic()
        ticks0 = self.robot.start_tracking(belt.direction_base, belt.ticks_per_m, most_m, self.session,
                                           count=self.conveyor.ticks)
        over["tracking"] = time.monotonic() - t0
        self.queue.remove(part)
        self._cycle = (cand, picture, T_place)
        try:
            T_pick, T_app = (part.T_at(belt, ticks0, T) for T in (cand.T_pick, cand.T_approach))
            for T, what in ((T_pick, "pick"), (T_app, "post-pick")):
                end = T.copy()
                end[:3, 3] += belt.direction_base * most_m
                try:  # where the belt may carry the pose before tracking ends, too
                    self.robot.limits.check_pose(end)
                except MotionRejected as exc:
                    raise MotionRejected(f"the {what} pose followed to the window's end is refused: {exc}") from None
            self._move(T_pick, "down onto the part, following the belt", d)
            self._at("closing")
            check = self.gripper.close_and_check()
            self._close_s = max(GRIP_CLOSE_S, check.elapsed_s)
            d.add("gripper", check.elapsed_s)
            self._at("lifting")
            self._move(T_app, "up from the belt, following it", d)
        finally:
            t0 = time.monotonic()
            self.robot.stop_tracking()
            over["tracking"] += time.monotonic() - t0
        fields = {**self._belt_fields(part, meeting, ticks0), "waited_ms": round(waited_ms, 1), "overhead_ms": over,
                  "replans": replans}
        report = self.robot.tracking_report()  # measured by a host-side tracker (the UR's); None: not measured
        if report is not None:
            fields["tracking_error_mm"] = {"rms": report["rms_mm"], "max": report["max_mm"],
                                           "samples": report["samples"], "servo_steps": report["servo_steps"],
                                           **{k: report[k] for k in ("mean_along_mm", "stream_gap_ms", "feed_gap_ms",
                                                                     "sample_age_ms") if k in report}}
        if not check.held:
            c.grip_failures += 1
            self._record("grip_failed", cand, picture, d=d, t_cycle=t_cycle, belt=fields,
                         detail=f"{check.detail}; the part went on with the belt (it may have slipped)")
            return
        c.picked += 1
        claimed_s = self._claim_while_carrying(slot, n_slots, cand, T_place, T_place_app, d)
        over["claim"] = claimed_s
        claimed = self._put_down(T_place, T_place_app, d)
        c.placed += 1
        durations = d.as_ms(time.monotonic() - t_cycle)
        self.status.times.add(durations)
        fields["overhead_ms"] = {k: round(v * 1e3, 2) for k, v in over.items()}
        self._record("placed", cand, picture, slot=slot, T_place=T_place, d=d, t_cycle=t_cycle, durations=durations,
                     resolves=claimed, belt=fields)

    def _claim_while_carrying(self, slot: int, n_slots: int | None, cand: Any, T_place: np.ndarray,
                              T_place_app: np.ndarray, d: Durations) -> float:
        """Claim the slot on the run's store thread while the arm carries the part over it (the claim's
        fsyncs off the cycle's path); the part goes down only once the claim is stored (exactly once), and
        whatever ends the carry (a Stop, a fault) waits for the claim first, so the run's end settles it.
        The time (s) the cycle still waited for the claim."""
        poses = {"pick_pose": seen_fields(cand, None, None)["pick_pose"],
                 "place_pose": seen_fields(None, None, T_place)["place_pose"]}
        claim = self._writer.submit(functools.partial(self.slots.take, slot, n_slots, self._n + 1, poses))
        self._at("carrying", store=True, holding=True)  # queued after the claim: stored in this order
        try:
            self._move(T_place_app, "pre-place", d)
        finally:
            t0 = time.monotonic()
            try:
                claim.exception(CLAIM_WAIT_S)  # waits; a failed claim is raised below, after the wait
            except FutureTimeout:
                raise PickError(f"the slot's claim was not stored within {CLAIM_WAIT_S:g} s; the part is still "
                                "held over the place (check the store)") from None
        claim.result()
        return time.monotonic() - t0
