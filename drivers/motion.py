"""One motion owner per robot, the Stop latch, and the deadline of a move.

Every robot adapter has one ``MotionOwner`` (``RobotBase.motion``), and every caller that moves
the robot goes through it:

- A **session** owns the robot for a whole sequence (one move, a pick's approach/pick/retreat, a
  calibration routine's stations). While one is open, ``begin`` of another raises ``RobotBusy``:
  a second mover is refused, never queued or interleaved.
- A **still** session (``begin(still=True)``) holds the robot standing still for a measurement
  (a verify's shot): while one is open no session that moves is begun; it is refused only while
  a session moves the robot, may be taken while the robot is latched, and cannot move it itself.
- **Stop** (``RobotBase.stop``) halts the robot at once, aborts the open session (its current move
  raises ``RobotStopped``, its later moves are refused) and **latches**: every new session is
  refused with ``RobotStopped`` until ``resume``.
- A move gets a **deadline** from its distance and speed (``move_deadline_s``); a move that has
  not finished by then is stopped and raises ``DeviceTimeout``.
- Every change of the latch (``latch``, ``resume``) is told to the owner's **latch listeners**
  (``add_latch_listener``) as a ``LatchChange``: the service stores the latch through one, so it
  outlives a crash. Whatever latches the robot (a Stop, a controller that drops out) goes through
  ``latch``, so no latch escapes them.

This module is pure bookkeeping (threads and events); ``RobotBase`` calls the adapter's hooks.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from drivers.errors import DriverError

log = logging.getLogger(__name__)

# A move is given this many times its nominal duration, plus a slack (MotionLimits), to finish:
# real controllers accelerate and blend, so the nominal distance/speed is a lower bound.
DEADLINE_FACTOR = 1.5
DEADLINE_SLACK_S = 5.0


class RobotBusy(DriverError):
    """Another caller owns the robot's motion (a move, a pick or a routine is running)."""


class RobotStopped(DriverError):
    """The robot was stopped: the move was halted, or the robot is latched until an engineer resumes."""


@dataclass(eq=False)
class MotionSession:
    """The right to move one robot, held by one caller for one sequence of moves.

    A ``still`` session holds the robot standing still for a measurement instead: nothing moves
    the robot while it is open, and it cannot move the robot itself.
    """

    robot_id: str
    who: str
    what: str
    started_s: float = field(default_factory=time.time)
    _aborted: threading.Event = field(default_factory=threading.Event)
    abort_reason: str = ""
    closed: bool = False
    still: bool = False

    @property
    def aborted(self) -> bool:
        return self._aborted.is_set()

    def abort(self, reason: str) -> None:
        if not self._aborted.is_set():
            self.abort_reason = reason
            self._aborted.set()

    def check(self) -> None:
        """Raise ``RobotStopped`` once the session was aborted by a Stop."""
        if self._aborted.is_set():
            raise RobotStopped(f"robot {self.robot_id}: {self.what} was stopped ({self.abort_reason}); "
                               "nothing more is moved in this sequence")
        if self.closed:
            raise RobotBusy(f"robot {self.robot_id}: the motion session of {self.what} has ended; start a new one")

    def wait_aborted(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for an abort; True when aborted."""
        return self._aborted.wait(timeout_s)


@dataclass(frozen=True)
class LatchChange:
    """One change of a robot's Stop latch, as its listeners see it."""

    robot_id: str
    latched: bool
    """True: the robot was latched (again); False: an engineer cleared the latch."""
    by: str
    """Who latched it, or who cleared it."""
    reason: str
    """Why it was latched ("Stop", a controller dropout ...); "resume" when cleared."""
    at_s: float
    """When, seconds since the Unix epoch (for a latch: the time it is latched since)."""
    seq: int
    """1, 2, ... per owner in the order of the changes (listeners may be told out of order)."""


LatchListener = Callable[[LatchChange], None]


class MotionOwner:
    """The owner of one robot's motion and its Stop latch (thread-safe)."""

    def __init__(self, robot_id: str) -> None:
        self.robot_id = robot_id
        self._lock = threading.Lock()
        self._session: MotionSession | None = None
        self._latched_by: str | None = None
        self._latched_reason = ""
        self._latched_s: float | None = None
        self._seq = 0
        self._listeners: list[LatchListener] = []
        self._holders: list[MotionSession] = []

    def add_latch_listener(self, listener: LatchListener) -> None:
        """Call ``listener`` with every later change of the latch.

        It is called in the thread that changed the latch, after the change took effect: it must
        return at once (queue its work). Its failure is logged and never undoes or delays a latch.
        """
        with self._lock:
            self._listeners.append(listener)

    def remove_latch_listener(self, listener: LatchListener) -> None:
        with self._lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def _changed(self, latched: bool, by: str, reason: str, at_s: float) -> tuple[LatchChange, list[LatchListener]]:
        """The change to tell (call under the lock) and the listeners to tell it to."""
        self._seq += 1
        return LatchChange(self.robot_id, latched, by, reason, at_s, self._seq), list(self._listeners)

    def _tell(self, change: LatchChange, listeners: list[LatchListener]) -> None:
        for listener in listeners:
            try:
                listener(change)
            except Exception:  # noqa: BLE001 - a listener never undoes or delays the latch
                log.exception("robot %s: a latch listener failed on %s", self.robot_id, change)

    def begin(self, who: str, what: str, still: bool = False) -> MotionSession:
        """Open a session for ``who`` doing ``what``; ``RobotStopped`` when latched, ``RobotBusy`` when owned.

        ``still``: hold the robot standing still for a measurement (refused only while a session
        moves it; a latched robot stands still, so it may be held). Several may hold it at once; while
        one does, a session that would move it is refused, and a Stop does not abort it.
        """
        with self._lock:
            if self._latched_by is not None and not still:
                raise RobotStopped(
                    f"robot {self.robot_id} is stopped (by {self._latched_by}: {self._latched_reason}); "
                    f"an engineer must resume it (POST /robots/{self.robot_id}/resume) before it moves again")
            current = self._session
            if current is not None:
                raise RobotBusy(f"robot {self.robot_id} is busy: {current.what} (started by {current.who}) "
                                "owns its motion; wait for it to finish or stop it")
            session = MotionSession(self.robot_id, who, what, still=still)
            if still:
                self._holders.append(session)
                return session
            if self._holders:
                h = self._holders[0]
                raise RobotBusy(f"robot {self.robot_id} is busy: {h.what} (started by {h.who}) holds it still "
                                "for a measurement; wait for it to finish")
            self._session = session
            return session

    def end(self, session: MotionSession) -> None:
        """Close ``session``; the robot is free for the next caller (safe to call twice)."""
        with self._lock:
            session.closed = True
            if self._session is session:
                self._session = None
            self._holders = [h for h in self._holders if h is not session]

    def is_current(self, session: MotionSession) -> bool:
        """True while ``session`` owns the robot's motion (may move it)."""
        with self._lock:
            return self._session is session

    def holds(self, session: MotionSession) -> bool:
        """True while ``session`` owns the robot: moves it, or holds it still."""
        with self._lock:
            return self._session is session or any(h is session for h in self._holders)

    def latch(self, who: str, reason: str = "Stop", since_s: float | None = None) -> MotionSession | None:
        """Latch the robot stopped and abort the session that owns it (returned, if any).

        ``since_s``: when the latch began, when it is older than this call (a latch carried over a
        restart); default now.
        """
        with self._lock:
            self._latched_by = who or "unknown"
            self._latched_reason = reason
            self._latched_s = time.time() if since_s is None else since_s
            session = self._session
            change = self._changed(True, self._latched_by, reason, self._latched_s)
        if session is not None:
            session.abort(f"{reason} by {who or 'unknown'}")
        self._tell(*change)
        return session

    def latch_if_owned(self, who: str, reason: str) -> MotionSession | None:
        """``latch`` only while a session owns the motion and no latch is set (a controller lost
        mid-sequence); the session it aborted, or None."""
        with self._lock:
            if self._session is None or self._latched_by is not None:
                return None
        return self.latch(who, reason)

    def resume(self, by: str = "") -> bool:
        """Clear the latch (``by``: the engineer who resumed); True when the robot was latched."""
        with self._lock:
            was = self._latched_by is not None
            self._latched_by = None
            self._latched_reason = ""
            self._latched_s = None
            change = self._changed(False, by or "unknown", "resume", time.time()) if was else None
        if change is not None:
            self._tell(*change)
        return was

    @property
    def latched(self) -> bool:
        with self._lock:
            return self._latched_by is not None

    def status(self) -> dict[str, Any]:
        """What a PLC or the page shows: latched (by whom, why, since), and who owns the motion."""
        with self._lock:
            s = self._session or (self._holders[0] if self._holders else None)
            return {
                "latched": self._latched_by is not None,
                "latched_by": self._latched_by,
                "latched_reason": self._latched_reason or None,
                "latched_since_s": self._latched_s,
                "owner": None if s is None else {"who": s.who, "what": s.what, "since_s": s.started_s,
                                                 "still": s.still},
            }


def move_deadline_s(nominal_s: float, slack_s: float = DEADLINE_SLACK_S) -> float:
    """Time a move with nominal duration ``nominal_s`` may take before it is stopped."""
    return nominal_s * DEADLINE_FACTOR + slack_s
