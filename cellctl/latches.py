"""The Stop latch as stored state: it outlives a crash and a restart of the service.

``LatchKeeper.restore`` runs at start-up, before anything is served: every robot the store holds
latched is latched again (with who latched it, why and since when), and the audit says so
("latched at start: stopped before the restart at ... by ..."). A store whose latches cannot be
read latches every robot instead (fail safe: an engineer resumes after checking the cell).

Then the keeper listens to every robot's motion owner (``drivers.motion``): each change of a latch
— a Stop, a controller that dropped out, an engineer's resume — is written to the store with its
audit entry by one writer thread, in order. The latch itself never waits on the store (a Stop
halts at once); the REST Stop and resume answer once their change is stored (``wait_stored``). A
change the store cannot take (a database outage) is retried every ``RETRY_S`` until it is stored.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Mapping

from cellctl.store import Store
from cellctl.store.latches import AUDIT_ACTION
from drivers.motion import LatchChange, MotionOwner

log = logging.getLogger(__name__)

RETRY_S = 1.0
"""A latch change the store refused is tried again after this many seconds."""
UNREADABLE_REASON = "the stored latches could not be read at start"


def when_text(at_s: float) -> str:
    """``at_s`` (seconds since the Unix epoch) as UTC for people: ``2026-12-02 09:50:01 UTC``."""
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(at_s))


class LatchKeeper:
    """Keeps the robots' latches in the store: restores them at start, writes every change."""

    def __init__(self, store: Store, owners: Mapping[str, MotionOwner]) -> None:
        self.store = store
        self.owners = dict(owners)
        self._cond = threading.Condition()
        self._pending: deque[tuple[int, LatchChange]] = deque()
        self._issued = 0
        self._written = 0
        self._last_seq: dict[str, int] = {}
        self._waiters: list[tuple[int, concurrent.futures.Future[bool]]] = []
        self._closing = False
        self._failing = False
        """The store refused the newest write: it is retried every ``RETRY_S``, and each refusal answers
        the waiters of that moment False (a Stop's answer does not wait out its whole timeout)."""
        self._thread: threading.Thread | None = None

    # -- start-up --------------------------------------------------------------------------------
    def restore(self) -> list[str]:
        """Latch again every configured robot the store holds latched; the ids latched (before serving)."""
        try:
            stored = self.store.latches()
        except Exception as exc:  # noqa: BLE001 - unreadable latches latch everything (fail safe)
            log.error("the stored robot latches cannot be read (%s): latching every robot until an engineer "
                      "resumes it", exc)
            for robot_id, each in self.owners.items():
                each.latch("cellctl", f"{UNREADABLE_REASON} ({exc})")
                self._audit_quietly(robot_id, f"latched at start: {UNREADABLE_REASON} ({exc})")
            return sorted(self.owners)
        latched = []
        for latch in stored:
            owner = self.owners.get(latch.robot_id)
            if owner is None:
                log.warning("robot %s is stored latched but not in the config; its latch stays stored",
                            latch.robot_id)
                continue
            owner.latch(latch.latched_by, latch.reason, since_s=latch.since_s)
            note = (f"latched at start: stopped before the restart at {when_text(latch.since_s)} by "
                    f"{latch.latched_by} ({latch.reason})")
            log.warning("robot %s %s; an engineer must resume it", latch.robot_id, note)
            try:
                self.store.set_latch(latch.robot_id, latch.latched_by, latch.reason, latch.since_s, result=note)
            except Exception as exc:  # noqa: BLE001 - the robot is latched; only the note is missing
                log.error("robot %s: auditing its latch carried over the restart failed: %s", latch.robot_id, exc)
            latched.append(latch.robot_id)
        return latched

    def _audit_quietly(self, robot_id: str, result: str) -> None:
        try:
            self.store.audit("cellctl", AUDIT_ACTION, robot_id, {"latched": True}, result)
        except Exception as exc:  # noqa: BLE001 - the store is the trouble here; the log has it
            log.error("robot %s: auditing its latch failed: %s", robot_id, exc)

    def start(self) -> None:
        """Listen to every robot's latch and start the writer (after ``restore``)."""
        self._thread = threading.Thread(target=self._run, name="latch-writer", daemon=True)
        self._thread.start()
        for owner in self.owners.values():
            owner.add_latch_listener(self._on_change)

    # -- the writer ------------------------------------------------------------------------------
    def _on_change(self, change: LatchChange) -> None:
        with self._cond:
            self._issued += 1
            self._pending.append((self._issued, change))
            self._cond.notify_all()

    def written(self) -> concurrent.futures.Future[bool]:
        """A future that becomes True once every change told so far is stored (False: the keeper closed first)."""
        fut: concurrent.futures.Future[bool] = concurrent.futures.Future()
        with self._cond:
            if self._written >= self._issued:
                fut.set_result(True)
            elif self._closing:
                fut.set_result(False)
            else:
                self._waiters.append((self._issued, fut))
        return fut

    async def wait_stored(self, timeout_s: float) -> bool:
        """Wait (without a thread) until every change told so far is stored; False after ``timeout_s``."""
        try:
            return await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(self.written())), timeout_s)
        except TimeoutError:
            return False

    def wait_stored_blocking(self, timeout_s: float) -> bool:
        """As ``wait_stored``, for a caller in a worker thread."""
        try:
            return self.written().result(timeout_s)
        except TimeoutError:
            return False

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closing:
                    self._cond.wait()
                if not self._pending:
                    return
                ticket, change = self._pending[0]
            try:
                self._store(change)
            except Exception as exc:  # noqa: BLE001 - retried until stored; the latch in memory holds meanwhile
                if not self._failing:
                    log.error("robot %s: storing its latch change (%s by %s) failed: %s; retrying every %.0f s",
                              change.robot_id, "latched" if change.latched else "cleared", change.by, exc, RETRY_S)
                with self._cond:
                    self._failing = True
                    self._resolve(None, False)  # waiters get their answer now: not stored (yet)
                    if self._closing:
                        log.error("robot %s: the latch change was NOT stored before the service stopped",
                                  change.robot_id)
                        self._pending.popleft()
                        continue
                    self._cond.wait(RETRY_S)
                continue
            if self._failing:
                log.warning("robot %s: latch change stored after the store came back", change.robot_id)
            with self._cond:
                self._failing = False
                self._pending.popleft()
                self._written = ticket
                self._resolve(ticket, True)

    def _store(self, change: LatchChange) -> None:
        if change.seq <= self._last_seq.get(change.robot_id, 0):
            return  # told after a newer change of the same robot: the newer one is the state
        if change.latched:
            self.store.set_latch(change.robot_id, change.by, change.reason, change.at_s)
        else:
            self.store.clear_latch(change.robot_id, change.by)
        self._last_seq[change.robot_id] = change.seq

    def _resolve(self, up_to: int | None, value: bool) -> None:
        """Resolve the waiters whose ticket is ``up_to`` or older (None: all), under the condition."""
        keep = []
        for t, fut in self._waiters:
            if up_to is not None and t > up_to:
                keep.append((t, fut))
                continue
            with contextlib.suppress(concurrent.futures.InvalidStateError):  # cancelled by its waiter
                fut.set_result(value)
        self._waiters = keep

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop listening, store what is pending (waiting up to ``timeout_s``), end the writer."""
        for owner in self.owners.values():
            owner.remove_latch_listener(self._on_change)
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
        with self._cond:
            if self._pending:
                log.error("%d latch change(s) were not stored before the service stopped", len(self._pending))
            self._resolve(None, False)
