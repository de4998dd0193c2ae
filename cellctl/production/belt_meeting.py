"""A belt run's meeting with a part: which part, where and when the arm meets it, the arm there, the wait.

The part furthest along that the robot can still meet inside the window is taken (``plan_meeting`` with the
robot's own timing of its moves, ``RobotBase.linear_move_s``, plus the lead the run measured on its own
approaches, ``LEAD_SAMPLES``; the grasp folded to the one nearest the tool's yaw); a part that cannot be met
before it leaves the window is given up, counted ``missed_window`` and recorded. The arm moves above the
meeting point while the gripper opens (on the run's gripper thread), then waits for the count at which the
part is there; an arm there late (``LATE_MM``) plans the meeting again further along the window, from where it
is (at most ``REPLANS`` times). A belt that stopped or slowed while the arm waits is recorded ``belt_stopped``
(the part stays queued). Counts are read on the run's thread (for the plan and the wait) and every ``WATCH_S``
by the run's count watcher (``_watch_count``: a count that jumps is caught while the arm moves too); both
sample them into ``BeltWatch`` (the speed, a count that jumps).
The run itself (its threads, the cycle): :class:`cellctl.production.conveyor_run.ConveyorRun`.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
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
from cellctl.production.records import Durations
from cellctl.production.run import ProductionRun
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
WATCH_S = 0.05
"""How often the run's count watcher reads the encoder's count, s. The run's thread reads it only between its
steps: none for the ~2 s of a pick cycle's moves and gripper, and a jump read that much later looks like an
ordinary belt (4000 ticks over 0.7 s: under 600 mm/s), the queued parts then 400 mm off. Read every 50 ms, a
jump of more than twice the belt's 300 mm/s over one period (30 mm) is caught within a period whatever the arm
is doing, the arm halted there; the watcher costs ~2 ms of CPU per second of run (docs/conveyor.md)."""


class BeltMeetingRun(ProductionRun):
    """A production run that meets its parts on a moving belt: the belt, its queue and count, the plan and the
    meeting (the base of :class:`~cellctl.production.conveyor_run.ConveyorRun`)."""

    def __init__(self, *args: Any, belt: BeltCalibration, conveyor: ConveyorBase, window_mm: tuple[float, float],
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.belt, self.conveyor, self.window_mm = belt, conveyor, window_mm
        self.queue = BeltQueue(belt)
        self.watch = BeltWatch(belt.ticks_per_m)
        self._close_s = GRIP_CLOSE_S
        """The gripper's close time (the last measured, at least ``GRIP_CLOSE_S``), s: the follow takes it."""
        self._open_s = GRIP_CLOSE_S
        """The gripper's open time (the last measured), s: the approach takes at least this."""
        self._overruns: deque[float] = deque(maxlen=LEAD_SAMPLES)
        """How much longer than the robot's own timing (plus the gripper's open) each approach took, s."""
        self._opener: ThreadPoolExecutor | None = None
        """Opens the gripper while the arm travels to the meeting point (the run's; shut down at its end)."""
        self._count_fault: str | None = None
        """Why the count watcher ended the run (a count that jumped; set before it aborts the motion session)."""

    def _check_count(self) -> int:
        """The encoder's count now, sampled by the watch (the run's thread); a count that jumped is raised, here
        or by the count watcher before."""
        if self._count_fault is not None:
            raise PickError(self._count_fault)
        ticks, problem = self.watch.read(self.conveyor.ticks)
        if problem is not None:
            raise PickError(problem)
        return ticks

    def _watch_count(self, halt: threading.Event) -> None:
        """The run's count watcher (its own thread, until ``halt``): the count read every ``WATCH_S`` into the
        watch. A count that jumps (or cannot be read) ends the run now: the reason kept (``_count_fault``, what
        the run fails with), the motion session aborted (a move under way raises, nothing more moves) and the
        arm halted, tracking too; the run's thread then ends the run ``failed`` with the reason."""
        while not halt.wait(WATCH_S):
            try:
                problem = self.watch.read(self.conveyor.ticks)[1]
            except Exception as exc:  # noqa: BLE001 - the run fails saying why, as a read on its thread would
                problem = f"reading the encoder's count failed: {exc}"
            if problem is not None:
                self._count_fault = problem
                self.session.abort(problem)
                try:
                    self.robot.halt()
                except Exception as exc:  # noqa: BLE001 - the run's end halts it again and says so
                    log.error("robot %s: halting after '%s' failed: %s", self.robot.robot_id, problem, exc)
                return

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
