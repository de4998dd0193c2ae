"""The robots' Stop latches as stored state: which robot is latched, by whom, why, since when.

A latch is safety state, not a record: it must outlive a crash and a restart (the service latches
the stored robots again before it serves anything), so every change is written in one transaction
with its audit entry — a process killed at any moment leaves both or neither. One row per latched
robot in ``robot_latches``; clearing deletes the row. The table is not part of a backup's cell
tables: restoring old calibrations never latches or frees a robot.

Methods of :class:`cellctl.store.Store` (``set_latch``, ``clear_latch``, ``latches``): the store's one
write transaction, with the audit entry in it.
"""

from __future__ import annotations

import math
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa

from cellctl.store import schema as S
from cellctl.store.errors import InvalidInput

AUDIT_ACTION = "robot.latch"
"""The audit action of every stored change of a latch (set, cleared, carried over a restart)."""


@dataclass(frozen=True)
class StoredLatch:
    """A robot latched in the store: ``latched_by`` (a token's name or a component), ``reason`` ("Stop",
    a controller dropout ...), ``since_s`` (seconds since the Unix epoch)."""

    robot_id: str
    latched_by: str
    reason: str
    since_s: float


class LatchRows:
    """The robots' stored latches (mixed into ``Store``)."""

    cell_id: str
    if TYPE_CHECKING:
        def _write(self) -> AbstractContextManager[sa.Connection]: ...
        def _read(self) -> AbstractContextManager[sa.Connection]: ...
        def _audit(self, conn: sa.Connection, who: str, action: str, target: str, detail: dict[str, Any],
                   result: str, at_s: float | None = None) -> None: ...

    def set_latch(self, robot_id: str, latched_by: str, reason: str, since_s: float, result: str = "stored") -> None:
        """Store that ``robot_id`` is latched (replacing an older latch of it), with its audit entry."""
        _check(robot_id, "robot_id")
        _check(latched_by, "latched_by")
        if isinstance(since_s, bool) or not isinstance(since_s, int | float) or not math.isfinite(since_s):
            raise InvalidInput(f"set_latch: since_s must be a finite time in seconds, got {since_s!r}")
        t = S.latches
        with self._write() as conn:
            conn.execute(t.delete().where(t.c.cell_id == self.cell_id, t.c.robot_id == robot_id))
            conn.execute(t.insert().values(cell_id=self.cell_id, robot_id=robot_id, latched_by=latched_by,
                                           reason=reason, since_s=float(since_s)))
            self._audit(conn, latched_by, AUDIT_ACTION, robot_id,
                        {"latched": True, "latched_by": latched_by, "reason": reason, "since_s": float(since_s)},
                        result)

    def clear_latch(self, robot_id: str, who: str, result: str = "stored: cleared") -> bool:
        """Store that ``robot_id`` is no longer latched (``who`` resumed it), with its audit entry.

        True when a stored latch was cleared; the audit entry is written either way.
        """
        _check(robot_id, "robot_id")
        _check(who, "who")
        t = S.latches
        with self._write() as conn:
            gone = conn.execute(t.delete().where(t.c.cell_id == self.cell_id, t.c.robot_id == robot_id)).rowcount
            self._audit(conn, who, AUDIT_ACTION, robot_id, {"latched": False, "resumed_by": who,
                                                             "was_stored": bool(gone)}, result)
        return bool(gone)

    def latches(self) -> list[StoredLatch]:
        """The robots stored latched (they are latched again when the service starts), by robot id."""
        t = S.latches
        with self._read() as conn:
            rows = conn.execute(sa.select(t.c.robot_id, t.c.latched_by, t.c.reason, t.c.since_s).where(
                t.c.cell_id == self.cell_id).order_by(t.c.robot_id)).all()
        return [StoredLatch(r.robot_id, r.latched_by, r.reason, float(r.since_s)) for r in rows]


def _check(value: object, what: str) -> None:
    if not isinstance(value, str) or not value.strip():
        raise InvalidInput(f"latch: {what} must be a non-empty string, got {value!r}")
