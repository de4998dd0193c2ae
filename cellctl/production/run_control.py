"""A production run's control and state: what other threads ask of it and read of it, and the states
it passes through between its cycles and at its end.

Safe from any thread (the run's condition): ``pause`` (the cycle in progress finishes, then
``pausing`` -> ``paused``), ``resume``, ``stop`` (after the cycle: ``stopping`` -> ``stopped``),
``abort`` (now: the motion session aborted, the robot halted, a held part stays gripped), ``join``;
``public`` (REST's view, reads the store once the run ended) and ``snapshot`` (a PLC's, from memory
only). The run's thread (:class:`cellctl.production.run.ProductionRun`) asks ``_between_cycles``
what happens before each cycle and ends with ``_end``; every change of state is stored in order by
the run's writer thread.
"""

from __future__ import annotations

import threading
from typing import Any

from cellctl.production.recorder import CycleLog
from cellctl.production.records import clean
from cellctl.production.slots import SlotClaims
from cellctl.production.status import Ended, Phase, RunSettings, RunStatus, State
from cellctl.production.writer import Writer
from cellctl.store import Store
from drivers.base import MotionSession, RobotBase


class RunControl:
    """Pause, resume, stop, abort and the run's state (the base of every production run)."""

    s: RunSettings
    store: Store
    robot: RobotBase
    session: MotionSession
    slots: SlotClaims
    cycles: CycleLog
    phase: Phase
    done: threading.Event
    _thread: threading.Thread
    _writer: Writer

    def __init__(self, status: RunStatus) -> None:
        self.status = status
        self._cond = threading.Condition()
        self._pause = False
        self._stop = False
        self._abort_reason: str | None = None

    @property
    def _n(self) -> int:
        return self.cycles.n

    @property
    def last_record(self) -> dict[str, Any] | None:
        """The last cycle's record (what a PLC reads as the last cycle's result)."""
        return self.cycles.last

    # -- control ----------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def pause(self) -> None:
        with self._cond:
            if self.status.state == "running":
                self._pause = True
                self.status.state = "pausing"
            self._cond.notify_all()

    def resume(self) -> None:
        with self._cond:
            self._pause = False
            if self.status.state in ("pausing", "paused"):
                self.status.state = "running"
            self._cond.notify_all()

    def stop(self, reason: str = "stopped by an operator (after the cycle in progress)") -> None:
        with self._cond:
            self._stop = True
            if self.status.stop_reason is None:
                self.status.stop_reason = reason
            if self.status.state in ("running", "pausing", "paused"):
                self.status.state = "stopping"
            self._cond.notify_all()

    def abort(self, reason: str) -> None:
        """End the run now (the service is shutting down): the motion session is aborted and the robot
        halted without a latch; the run ends ``stopped`` with ``reason``; a held part stays gripped."""
        self._abort_reason = reason
        self.stop(reason)
        self.session.abort(reason)
        try:
            self.robot.halt()
        finally:
            with self._cond:
                self._cond.notify_all()

    def join(self, timeout_s: float | None = None) -> None:
        self._thread.join(timeout_s)

    @property
    def ended(self) -> bool:
        return self.done.is_set()

    def public(self) -> dict[str, Any]:
        st = self.status
        return {"run_id": st.run_id, "recipe_id": st.recipe_id, "robot_id": st.robot_id, "state": st.state,
                "ended_because": st.ended_because, "counters": st.counters.as_dict(), "cycle_ms": st.times.summary(),
                "next_slot": self.store.free_slot(st.recipe_id) if self.ended else self.slots.next_slot,
                "error": st.error, "stop_reason": st.stop_reason, "cycles": self._n, "phase": self.phase}

    def snapshot(self) -> dict[str, Any]:
        """The run as a PLC reads it, from memory only (no store access: safe on a server's event loop)."""
        st = self.status
        return {"run_id": st.run_id, "state": st.state, "ended_because": st.ended_because,
                "counters": st.counters.as_dict(), "next_slot": self.slots.next_slot,
                "cycle_median_ms": st.times.summary()["median"], "last": self.last_record}

    # -- the states between cycles and at the end ---------------------------------------------------
    def _between_cycles(self) -> Ended | None:
        """Stop, pause, or the count reached: what happens before the next cycle starts."""
        with self._cond:
            if self._stop:
                return "stopped"
            if self.s.count and self.status.counters.placed >= self.s.count:
                return "count_reached"
            if self._pause:
                self.status.state = "paused"
                self._store_state()
                while self._pause and not self._stop and not self.session.aborted:
                    self._cond.wait(0.2)
                if self._stop:
                    return "stopped"
                self.session.check()
                self.status.state = "running"
        self._store_state()
        return None

    def _end(self, state: State, ended: Ended, error: str | None = None) -> None:
        self._writer.flush()  # a client that sees the run ended finds every cycle record stored
        # ... and finds the robot free: a PLC or an engineer acting on "ended" is not refused robot_busy.
        self.robot.motion.end(self.session)
        with self._cond:
            self.status.state = state
            self.status.ended_because = ended
            self.status.error = error
            self._cond.notify_all()
        summary = clean(self._summary())
        self._writer.put(lambda: self.store.update_run(self.status.run_id, state, ended, summary, ended=True))

    def _summary(self) -> dict[str, Any]:
        st = self.status
        return {"counters": st.counters.as_dict(), "cycle_ms": st.times.summary(), "error": st.error,
                "stop_reason": st.stop_reason, "cycles": self._n}

    def _store_state(self) -> None:
        state, summary = self.status.state, clean(self._summary())
        self._writer.put(lambda: self.store.update_run(self.status.run_id, state, None, summary))
