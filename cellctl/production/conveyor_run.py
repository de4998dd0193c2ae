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
``stopped``. Faults end the run ``failed`` with the reason: a count that jumps (faster than any belt),
an encoder that stopped while the parts moved (two pictures at one count, the parts elsewhere), a
belt that stopped with the robot waiting for a part (``belt_stopped`` is recorded; the part stays
queued and is met where it lies if that is in the window).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures import wait as futures_wait
from typing import Any

import numpy as np

from cellctl.pick.candidate import PickCandidate
from cellctl.pick.recipe import PickError
from cellctl.production.belt import (
    BeltCalibration,
    BeltPart,
    BeltQueue,
    BeltWatch,
    Meeting,
    Missed,
    grasp_near,
    plan_meeting,
)
from cellctl.production.place import place_poses
from cellctl.production.records import Durations, seen_fields
from cellctl.production.run import ProductionRun
from cellctl.production.status import Ended
from cellctl.production.vision import take_picture
from drivers.base import MotionRejected
from drivers.conveyor.base import ConveyorBase
from drivers.robot_base import DEFAULT_ACCEL_M_S2

log = logging.getLogger(__name__)

POLL_S = 0.002
"""How often the count is read while the robot waits for a part, s."""
FOLLOW_MARGIN_S = 0.25
"""Added to the follow time (down, close, up) when a meeting is planned, s."""
GRIP_CLOSE_S = 0.2
"""The gripper's close time assumed until the run has measured one, s."""
LEAD_S = 0.05
"""The least time planned between a meeting's plan and the arm above the meeting point besides the move itself
(the move's start, the host's delays), s; the run learns more from its moves (``LEAD_SAMPLES``)."""
LEAD_SAMPLES = 8
"""The lead is the longest of the last this many approach moves' overruns of the robot's own timing."""
LATE_MM = 2.0
"""The arm above the meeting point later than the part by more than this (mm of belt): the meeting is planned
again further along the window (never past it), from where the arm is."""
REPLANS = 3
"""At most this many later meetings for one part before it is given up as missed."""
WAIT_SLACK_S = 1.5
"""The robot waits this much longer than planned for the count at which the part is under it, s."""
CLAIM_WAIT_S = 30.0
"""The longest the arm waits over the place for the slot's claim to be stored, s."""
ENCODER_STOP_S = 0.3
"""Two pictures this far apart in time at one count, the parts elsewhere: the encoder stopped."""


class ConveyorRun(ProductionRun):
    """A production run whose parts come on a belt (one per robot, like a still run)."""

    def __init__(self, *args: Any, belt: BeltCalibration, conveyor: ConveyorBase, window_mm: tuple[float, float],
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.belt, self.conveyor, self.window_mm = belt, conveyor, window_mm
        self.queue = BeltQueue(belt)
        self.watch = BeltWatch(belt.ticks_per_m)
        self._fault: str | None = None
        self._seen_s = time.monotonic()
        self._halt_vision = threading.Event()
        self._close_s = GRIP_CLOSE_S
        self._open_s = GRIP_CLOSE_S
        """The gripper's open time (the last measured), s: the approach takes at least this."""
        self._overruns: deque[float] = deque(maxlen=LEAD_SAMPLES)
        """How much longer than the robot's own timing (plus the gripper's open) each approach took, s."""
        self._opener: ThreadPoolExecutor | None = None
        """Opens the gripper while the arm travels to the meeting point (the run's; shut down at its end)."""
        self.pictures = 0

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
        while not self._halt_vision.is_set():
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
        looker = threading.Thread(target=self._look, name=f"production-{self.status.run_id}-belt", daemon=True)
        looker.start()
        self._opener = ThreadPoolExecutor(1, thread_name_prefix=f"production-{self.status.run_id}-gripper")
        try:
            return self._belt_cycles()
        finally:
            self._halt_vision.set()
            self._opener.shutdown(wait=True)
            looker.join(30.0)

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

    def _check_count(self) -> int:
        read_from_s = time.monotonic()
        ticks = self.conveyor.ticks()
        problem = self.watch.sample(ticks, read_from_s=read_from_s)
        if problem is not None:
            raise PickError(problem)
        return ticks

    def _follow_s(self, cand: PickCandidate | None = None) -> float:
        """The time the arm follows a part: down to it, the gripper's close, up (the robot's own timing of the
        two moves), and ``FOLLOW_MARGIN_S``, s."""
        r = self.s.recipe
        if cand is None:
            T_app = np.eye(4)
            T_app[2, 3] = r.approach_height_mm * 1e-3
            T_pick = np.eye(4)
        else:
            T_app, T_pick = cand.T_approach, cand.T_pick
        moves = self._move_s(T_app, T_pick) + self._move_s(T_pick, T_app)
        return moves + self._close_s + FOLLOW_MARGIN_S

    def _move_s(self, T_from: np.ndarray, T_to: np.ndarray) -> float:
        """The robot's own timing of a linear move at the recipe's speed and the belt source's acceleration, s."""
        r = self.s.recipe
        accel = r.source.accel_m_s2 if r.source is not None else DEFAULT_ACCEL_M_S2
        return self.robot.linear_move_s(T_from, T_to, r.speed_m_s, accel)

    def _approach_s(self, T_from: np.ndarray, T_to: np.ndarray) -> float:
        """The approach's planned time: the move, or the gripper's open that runs during it when longer, s."""
        return max(self._move_s(T_from, T_to), self._open_s)

    def _lead_s(self) -> float:
        """What the plan adds to the robot's own timing of the approach: the longest recent overrun, at least
        ``LEAD_S``."""
        return max([LEAD_S, *self._overruns])

    def _plan(self, part: BeltPart, ticks: int, T_tool: np.ndarray) -> Meeting | str:
        """The meeting of ``part`` from the tool at ``T_tool`` at count ``ticks`` (``plan_meeting`` with the
        robot's own timing of the move)."""
        r = self.s.recipe
        if r.source is None:
            raise PickError("a belt run needs a recipe with source: {kind: conveyor}")
        return plan_meeting(part, self.belt, ticks, self.watch.speed_mm_s(), T_tool[:3, 3],
                            float(part.cand.T_approach[2, 3]), self.window_mm, r.speed_m_s, r.source.accel_m_s2,
                            self._follow_s(part.cand), travel=functools.partial(self._approach_s, T_tool),
                            lead_s=self._lead_s())

    def _next_part(self) -> tuple[BeltPart, Meeting] | None:
        """The part furthest along that can be met (and its meeting); parts that cannot are given up. Each
        part's grasp is folded to the one nearest the tool's yaw now (the least turn on the way)."""
        ticks = self._check_count()
        tool = self.robot.state().T_base_tool
        for part in self.queue.downstream_first(ticks):
            part.cand = grasp_near(self.s.recipe, part.cand, tool, self.robot.limits)
            plan = self._plan(part, ticks, tool)
            if isinstance(plan, Meeting):
                return part, plan
            if isinstance(plan, Missed):
                self._missed(part, str(plan))
        return None

    def _missed(self, part: BeltPart, why: str) -> None:
        self.queue.remove(part)
        self.status.counters.missed_window += 1
        self._record("missed_window", part.cand, part.picture, detail=f"left unpicked: {why}",
                     belt=self._belt_fields(part, None))

    def _belt_fields(self, part: BeltPart, meeting: Meeting | None, ticks0: int | None = None) -> dict[str, Any]:
        return {"conveyor_id": self.conveyor.conveyor_id, "seen_ticks": part.ticks, "sightings": part.sightings,
                "meet_ticks": None if meeting is None else meeting.ticks,
                "meet_x_mm": None if meeting is None else round(meeting.x_mm, 2), "tracking_ticks": ticks0,
                "speed_mm_s": round(self.watch.speed_mm_s(), 1)}

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

    def _meet(self, part: BeltPart, meeting: Meeting, d: Durations, t_plan: float
              ) -> tuple[int, Meeting, float, int] | None:
        """Move above the meeting point (the gripper opening meanwhile) and wait for the part: (the count when
        it is there, the meeting kept, the wait in ms, how many times it was planned again). An arm there later
        than the part (by more than ``LATE_MM``), or too late to follow it while it grips before the window's
        end, plans the meeting again from where it is, further along the window (at most ``REPLANS`` times);
        a part that then cannot be met is given up, counted ``missed_window`` (None). None too when the belt
        stopped or slowed (the part stays queued)."""
        belt = self.belt
        waited_ms, replans = 0.0, 0
        while True:
            T_from = self.robot.state().T_base_tool
            T_app = part.T_at(belt, meeting.ticks, part.cand.T_approach)
            planned_s = self._approach_s(T_from, T_app)
            self._open_s = self._approach(T_app, d)
            self._overruns.append(max(0.0, time.monotonic() - t_plan - planned_s))
            t_wait = time.monotonic()
            ticks = self._wait_for(part, meeting)
            waited_ms += (time.monotonic() - t_wait) * 1e3
            if ticks is None:
                return None
            x_part = part.x_at(belt, ticks)
            late_mm = (ticks - meeting.ticks) / belt.ticks_per_m * 1e3
            room_mm = self.window_mm[1] - x_part
            if late_mm <= LATE_MM and room_mm >= self.watch.speed_mm_s() * self._follow_s(part.cand) - LATE_MM:
                return ticks, meeting, waited_ms, replans
            why = (f"the robot was above the meeting point late ({late_mm:.0f} mm of belt): the part was at x = "
                   f"{x_part:.0f} mm, too near the window's end ({self.window_mm[1]:.0f} mm) to be followed while "
                   "gripped")
            if replans >= REPLANS:
                self._missed(part, why)
                return None
            t_plan = time.monotonic()
            plan = self._plan(part, self._check_count(), self.robot.state().T_base_tool)
            if not isinstance(plan, Meeting):
                self._missed(part, f"{why}; planned again: {plan}")
                return None
            meeting, replans = plan, replans + 1

    def _approach(self, T_app: np.ndarray, d: Durations) -> float:
        """Move above the meeting point while the gripper opens (on the run's gripper thread: the open is hidden
        behind the move); both done when this returns, a failed open raised after the move. The open's time, s."""
        if self._opener is None:  # a bug, not a plant's mistake: the run's start makes it
            raise RuntimeError("the belt run's gripper thread is not running")
        opening = self._opener.submit(self.gripper.open)
        try:
            self._move(T_app, "above the part's meeting point", d)
        finally:
            futures_wait([opening])
        return opening.result()

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

    def _wait_for(self, part: BeltPart, meeting: Meeting) -> int | None:
        """Wait until the count at which the part is under the tool; None when it does not come in time."""
        deadline = time.monotonic() + meeting.wait_s + WAIT_SLACK_S
        while True:
            ticks = self._check_count()
            if ticks >= meeting.ticks:
                return ticks
            self.session.check()
            if self._stop and self.status.state == "stopping":
                return None
            if time.monotonic() > deadline:
                self._record("belt_stopped", part.cand, part.picture, belt=self._belt_fields(part, meeting),
                             detail=f"the part did not reach the meeting point (count {ticks}, expected "
                                    f"{meeting.ticks}): the belt stopped or slowed; planned again")
                return None
            time.sleep(POLL_S)

