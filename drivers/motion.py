"""One motion owner per robot, the Stop latch, and the deadline of a move.

Every robot adapter has one ``MotionOwner`` (``RobotBase.motion``), and every caller that moves
the robot goes through it:

- A **session** owns the robot for a whole sequence (one move, a pick's approach/pick/retreat, a
  calibration routine's stations). While one is open, ``begin`` of another raises ``RobotBusy``:
  a second mover is refused, never queued or interleaved.
- **Stop** (``RobotBase.stop``) halts the robot at once, aborts the open session (its current move
  raises ``RobotStopped``, its later moves are refused) and **latches**: every new session is
  refused with ``RobotStopped`` until ``resume``.
- A move gets a **deadline** from its distance and speed (``move_deadline_s``); a move that has
  not finished by then is stopped and raises ``DeviceTimeout``.

This module is pure bookkeeping (threads and events); ``RobotBase`` calls the adapter's hooks.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from drivers.errors import DriverError

# A move is given this many times its nominal duration, plus a slack (MotionLimits), to finish:
# real controllers accelerate and blend, so the nominal distance/speed is a lower bound.
DEADLINE_FACTOR = 1.5
DEADLINE_SLACK_S = 5.0


class RobotBusy(DriverError):
    """Another caller owns the robot's motion (a move, a pick or a routine is running)."""


class RobotStopped(DriverError):
    """The robot was stopped: the move was halted, or the robot is latched until an engineer resumes."""


@dataclass
class MotionSession:
    """The right to move one robot, held by one caller for one sequence of moves."""

    robot_id: str
    who: str
    what: str
    started_s: float = field(default_factory=time.time)
    _aborted: threading.Event = field(default_factory=threading.Event)
    abort_reason: str = ""
    closed: bool = False

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


class MotionOwner:
    """The owner of one robot's motion and its Stop latch (thread-safe)."""

    def __init__(self, robot_id: str) -> None:
        self.robot_id = robot_id
        self._lock = threading.Lock()
        self._session: MotionSession | None = None
        self._latched_by: str | None = None
        self._latched_reason = ""
        self._latched_s: float | None = None

    def begin(self, who: str, what: str) -> MotionSession:
        """Open a session for ``who`` doing ``what``; ``RobotStopped`` when latched, ``RobotBusy`` when owned."""
        with self._lock:
            if self._latched_by is not None:
                raise RobotStopped(
                    f"robot {self.robot_id} is stopped (by {self._latched_by}: {self._latched_reason}); "
                    f"an engineer must resume it (POST /robots/{self.robot_id}/resume) before it moves again")
            current = self._session
            if current is not None:
                raise RobotBusy(f"robot {self.robot_id} is busy: {current.what} (started by {current.who}) "
                                "owns its motion; wait for it to finish or stop it")
            session = MotionSession(self.robot_id, who, what)
            self._session = session
            return session

    def end(self, session: MotionSession) -> None:
        """Close ``session``; the robot is free for the next caller (safe to call twice)."""
        with self._lock:
            session.closed = True
            if self._session is session:
                self._session = None

    def is_current(self, session: MotionSession) -> bool:
        with self._lock:
            return self._session is session

    def latch(self, who: str, reason: str = "Stop") -> MotionSession | None:
        """Latch the robot stopped and abort the session that owns it (returned, if any)."""
        with self._lock:
            self._latched_by = who or "unknown"
            self._latched_reason = reason
            self._latched_s = time.time()
            session = self._session
        if session is not None:
            session.abort(f"{reason} by {who or 'unknown'}")
        return session

    def resume(self) -> bool:
        """Clear the latch; True when the robot was latched."""
        with self._lock:
            was = self._latched_by is not None
            self._latched_by = None
            self._latched_reason = ""
            self._latched_s = None
            return was

    @property
    def latched(self) -> bool:
        with self._lock:
            return self._latched_by is not None

    def status(self) -> dict[str, Any]:
        """What a PLC or the page shows: latched (by whom, why, since), and who owns the motion."""
        with self._lock:
            s = self._session
            return {
                "latched": self._latched_by is not None,
                "latched_by": self._latched_by,
                "latched_reason": self._latched_reason or None,
                "latched_since_s": self._latched_s,
                "owner": None if s is None else {"who": s.who, "what": s.what, "since_s": s.started_s},
            }


def move_deadline_s(nominal_s: float, slack_s: float = DEADLINE_SLACK_S) -> float:
    """Time a move with nominal duration ``nominal_s`` may take before it is stopped."""
    return nominal_s * DEADLINE_FACTOR + slack_s
