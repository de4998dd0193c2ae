"""Production's stored state, as methods of :class:`cellctl.store.Store`: the runs, every cycle's
record, the next free place slot per recipe and the slots claimed for a part on its way.

The tables are the store's (``cellctl.store.schema``): written through the store's one write
transaction (the PostgreSQL advisory lock, the ``StoreUnavailable``/``StoreDamaged`` mapping), in
its backups, migrated with its schema.

Exactly once: a run *claims* its slot (one transaction: the claim row and the counter past it)
before it carries the part there, and *confirms* it once the gripper has let the part go; a run
that ends in between leaves the claim ``in_doubt`` (and a claim still ``claimed`` at the next start
belonged to a service that died: :meth:`ProductionRows.claims_in_doubt_at_start`). A slot with a
claim is never chosen (:meth:`ProductionRows.free_slot`) until an engineer confirms it
(:meth:`ProductionRows.confirm_slot`).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa

from cellctl.store import schema as S
from cellctl.store.errors import InvalidInput, NotFound, StoreError, StoreUnavailable
from cellctl.store.values import check_text, to_json_text

ENDED_STATES = ("stopped", "complete", "failed", "interrupted")
"""A run in one of these states has ended; any other stored state at a start means the service died."""
SLOT_CONFIRM_ACTION = "production.slot_confirm"
DOUBT_RETRY_S = 2.0
"""After the slots in doubt could not be read, the PLC front ends are told "not known" for this long
before the store is asked again (they read on every request; an unreachable database must not make
each of them wait for its connect timeout)."""

log = logging.getLogger(__name__)


class SlotTaken(StoreError):
    """The slot is claimed already (another run, or in doubt): the part is not carried there."""


@dataclass(frozen=True)
class DoubtSummary:
    """How many slots of the cell are in doubt, and the first of them (by recipe, then slot)."""

    count: int
    recipe_id: int | None = None
    """The first in-doubt slot's recipe; None when no slot is in doubt."""
    slot: int | None = None
    """The first in-doubt slot (0-based); None when no slot is in doubt."""


class ProductionRows:
    """Production's rows of one cell (mixed into ``Store``: the same connection pool and write path)."""

    cell_id: str
    _doubt_cache: tuple[int, DoubtSummary | None] = (0, None)
    """(generation, summary) of :meth:`doubt_summary`; every change of a claim's state moves the generation."""
    _doubt_lock = threading.Lock()
    _doubt_retry_at = 0.0
    """``time.monotonic()`` before which a failed read of the slots in doubt is not tried again."""
    if TYPE_CHECKING:
        def _write(self) -> AbstractContextManager[sa.Connection]: ...
        def _read(self) -> AbstractContextManager[sa.Connection]: ...
        def _loads(self, text: str, what: str) -> Any: ...
        def _audit(self, conn: sa.Connection, who: str, action: str, target: str, detail: dict[str, Any],
                   result: str, at_s: float | None = None) -> None: ...

    # -- the slot counter --------------------------------------------------------------------------
    def next_slot(self, recipe_id: int) -> int:
        """The recipe's next free place slot by its counter (0 when never set)."""
        with self._read() as conn:
            return self._next_slot(conn, recipe_id)

    def _next_slot(self, conn: sa.Connection, recipe_id: int) -> int:
        t = S.production_slots.c
        row = conn.execute(sa.select(t.next_slot).where(t.cell_id == self.cell_id, t.recipe_id == recipe_id)).first()
        return 0 if row is None else int(row[0])

    def set_next_slot(self, recipe_id: int, next_slot: int, who: str) -> None:
        with self._write() as conn:
            self._set_next_slot(conn, recipe_id, next_slot, who)

    def _set_next_slot(self, conn: sa.Connection, recipe_id: int, next_slot: int, who: str) -> None:
        t = S.production_slots
        key = (t.c.cell_id == self.cell_id) & (t.c.recipe_id == recipe_id)
        values = {"next_slot": int(next_slot), "who": who, "at_s": time.time()}
        if conn.execute(sa.update(t).where(key).values(**values)).rowcount == 0:
            conn.execute(t.insert().values(cell_id=self.cell_id, recipe_id=recipe_id, **values))

    def free_slot(self, recipe_id: int) -> int:
        """The slot the next part goes to: the counter's, or the first after it that no claim holds."""
        with self._read() as conn:
            slot = self._next_slot(conn, recipe_id)
            taken = self._claimed(conn, recipe_id)
        while slot in taken:
            slot += 1
        return slot

    def _claimed(self, conn: sa.Connection, recipe_id: int) -> set[int]:
        c = S.slot_claims.c
        return {int(s) for s in conn.execute(sa.select(c.slot).where(
            c.cell_id == self.cell_id, c.recipe_id == recipe_id)).scalars()}

    # -- claims ------------------------------------------------------------------------------------
    def claim_slot(self, recipe_id: int, slot: int, run_id: int, n: int, detail: dict[str, Any]) -> None:
        """Claim ``slot`` for the part run ``run_id`` carries in cycle ``n`` and move the counter past it,
        in one transaction; :class:`SlotTaken` when a claim holds it already."""
        with self._write() as conn:
            if slot in self._claimed(conn, recipe_id):
                raise SlotTaken(f"slot {slot} of recipe {recipe_id} is claimed already (in doubt, or another run's); "
                                "GET /production lists the slots in doubt")
            conn.execute(S.slot_claims.insert().values(
                cell_id=self.cell_id, recipe_id=recipe_id, slot=slot, run_id=run_id, n=n, state="claimed",
                at_s=time.time(), detail_json=to_json_text(detail, "slot claim detail")))
            if self._next_slot(conn, recipe_id) < slot + 1:
                self._set_next_slot(conn, recipe_id, slot + 1, f"production run {run_id}")

    def placed_in_slot(self, recipe_id: int, slot: int, run_id: int) -> None:
        """The run let its part go in ``slot``: the claim is resolved (the counter is past it already)."""
        c = S.slot_claims.c
        with self._write() as conn:
            conn.execute(S.slot_claims.delete().where(c.cell_id == self.cell_id, c.recipe_id == recipe_id,
                                                      c.slot == slot, c.run_id == run_id))

    def slot_in_doubt(self, recipe_id: int, slot: int, run_id: int, detail: dict[str, Any]) -> None:
        """The run ended without knowing whether its part is in ``slot``: keep the slot from every run."""
        c = S.slot_claims.c
        with self._write() as conn:
            conn.execute(sa.update(S.slot_claims).where(
                c.cell_id == self.cell_id, c.recipe_id == recipe_id, c.slot == slot, c.run_id == run_id).values(
                state="in_doubt", at_s=time.time(), detail_json=to_json_text(detail, "slot claim detail")))
        self.forget_doubt()

    def claims_in_doubt_at_start(self, why: str) -> list[dict[str, Any]]:
        """At the service's start (no run is alive): every claim still ``claimed`` becomes ``in_doubt``."""
        c = S.slot_claims.c
        out = []
        with self._write() as conn:
            rows = conn.execute(sa.select(S.slot_claims).where(c.cell_id == self.cell_id, c.state == "claimed")).all()
            for r in rows:
                detail = {**self._loads(r.detail_json, "a slot claim"), "in_doubt_because": why}
                conn.execute(sa.update(S.slot_claims).where(
                    c.cell_id == self.cell_id, c.recipe_id == r.recipe_id, c.slot == r.slot).values(
                    state="in_doubt", detail_json=to_json_text(detail, "slot claim detail")))
                out.append({"recipe_id": r.recipe_id, "slot": r.slot, "run_id": r.run_id, "n": r.n,
                            "since_s": r.at_s, **detail})
        self.forget_doubt()
        return out

    def slots_in_doubt(self, recipe_id: int | None = None) -> list[dict[str, Any]]:
        """The slots no run places into until an engineer confirms them, by recipe and slot."""
        c = S.slot_claims.c
        q = sa.select(S.slot_claims).where(c.cell_id == self.cell_id, c.state == "in_doubt")
        if recipe_id is not None:
            q = q.where(c.recipe_id == recipe_id)
        with self._read() as conn:
            rows = conn.execute(q.order_by(c.recipe_id, c.slot)).all()
        return [{"recipe_id": r.recipe_id, "slot": r.slot, "run_id": r.run_id, "n": r.n, "since_s": r.at_s,
                 **self._loads(r.detail_json, "a slot claim")} for r in rows]

    def confirm_slot(self, recipe_id: int, slot: int, occupied: bool, who: str) -> dict[str, Any]:
        """An engineer says what is in an in-doubt slot; audited in the same transaction.

        ``occupied``: the slot stays used. Not occupied: the claim goes and, when the counter is just
        past the slot, the counter goes back to it (the next part goes there). :class:`NotFound` when
        the slot is not in doubt.
        """
        check_text(who, "who")
        if not isinstance(occupied, bool):
            raise InvalidInput(f"confirm_slot: occupied must be true or false, got {occupied!r}")
        c = S.slot_claims.c
        with self._write() as conn:
            row = conn.execute(sa.select(S.slot_claims).where(
                c.cell_id == self.cell_id, c.recipe_id == recipe_id, c.slot == slot, c.state == "in_doubt")).first()
            if row is None:
                raise NotFound(f"slot {slot} of recipe {recipe_id} is not in doubt (GET /production lists the slots "
                               "in doubt)")
            conn.execute(S.slot_claims.delete().where(c.cell_id == self.cell_id, c.recipe_id == recipe_id,
                                                      c.slot == slot))
            counter = self._next_slot(conn, recipe_id)
            if not occupied and counter == slot + 1:
                self._set_next_slot(conn, recipe_id, slot, who)
                counter = slot
            out = {"recipe_id": recipe_id, "slot": slot, "occupied": occupied, "run_id": row.run_id, "n": row.n,
                   "next_slot": counter}
            self._audit(conn, who, SLOT_CONFIRM_ACTION, f"recipe:{recipe_id}", out, "ok")
        self.forget_doubt()
        return out

    def doubt_summary(self) -> DoubtSummary:
        """The count of slots in doubt and the first one, for the PLC front ends (read on every Modbus
        read, every 0.1 s by OPC UA, on their event loops): kept in memory. It is read again from the
        store by the thread that changed a claim's state through this store (a slot put in doubt, the
        claims of a dead service, a confirm, a restore), right after its write, so a PLC's read does
        not wait for the database; one service writes a cell's claims, so memory and store agree.
        When the store could not be read, :class:`StoreUnavailable` (retried after ``DOUBT_RETRY_S``)."""
        generation, summary = self._doubt_cache
        if summary is not None:
            return summary
        if time.monotonic() < self._doubt_retry_at:
            raise StoreUnavailable("the slots in doubt could not be read from the store; retrying shortly")
        c = S.slot_claims.c
        try:
            with self._read() as conn:
                count = int(conn.execute(sa.select(sa.func.count()).select_from(S.slot_claims).where(
                    c.cell_id == self.cell_id, c.state == "in_doubt")).scalar_one())
                first = conn.execute(sa.select(c.recipe_id, c.slot).where(
                    c.cell_id == self.cell_id, c.state == "in_doubt").order_by(c.recipe_id, c.slot).limit(1)).first()
        except StoreError:
            self._doubt_retry_at = time.monotonic() + DOUBT_RETRY_S  # a PLC read does not wait on it again at once
            raise
        summary = DoubtSummary(count, None if first is None else int(first.recipe_id),
                               None if first is None else int(first.slot))
        with self._doubt_lock:
            if self._doubt_cache[0] == generation:  # no change since the read began: keep it
                self._doubt_cache = (generation, summary)
        return summary

    def forget_doubt(self) -> None:
        """The slots in doubt changed: read them again now (in the caller's thread, which has just written
        to the store), or at the next :meth:`doubt_summary` when that fails."""
        with self._doubt_lock:
            self._doubt_cache = (self._doubt_cache[0] + 1, None)
            self._doubt_retry_at = 0.0
        try:
            self.doubt_summary()
        except Exception as exc:  # noqa: BLE001 - the write is done; the PLC reads "not known" meanwhile
            log.warning("the slots in doubt cannot be read from the store now: %s", exc)

    # -- runs --------------------------------------------------------------------------------------
    def new_run(self, recipe_id: int, robot_id: str, who: str) -> int:
        with self._write() as conn:
            return int(conn.execute(S.production_runs.insert().values(
                cell_id=self.cell_id, recipe_id=recipe_id, robot_id=robot_id, started_by=who, started_s=time.time(),
                state="running", summary_json="{}", progress_json="{}").returning(S.production_runs.c.id)).scalar_one())

    def update_run(self, run_id: int, state: str, ended_because: str | None, summary: dict[str, Any],
                   ended: bool = False) -> None:
        r = S.production_runs.c
        values: dict[str, Any] = {"state": state, "ended_because": ended_because,
                                  "summary_json": json.dumps(summary, allow_nan=False)}
        if ended:
            values["ended_s"] = time.time()
        with self._write() as conn:
            conn.execute(sa.update(S.production_runs).where(r.id == run_id, r.cell_id == self.cell_id).values(**values))

    def set_progress(self, run_id: int, progress: dict[str, Any]) -> None:
        """Where the run is in its cycle (read back when a run the service did not end is ended)."""
        r = S.production_runs.c
        with self._write() as conn:
            conn.execute(sa.update(S.production_runs).where(r.id == run_id, r.cell_id == self.cell_id).values(
                progress_json=to_json_text(progress, "run progress")))

    def get_run(self, run_id: int) -> dict[str, Any]:
        r = S.production_runs.c
        with self._read() as conn:
            row = conn.execute(sa.select(S.production_runs).where(r.id == run_id, r.cell_id == self.cell_id)).first()
        if row is None:
            raise NotFound(f"no production run {run_id} in cell {self.cell_id!r}")
        return {"run_id": row.id, "recipe_id": row.recipe_id, "robot_id": row.robot_id, "state": row.state,
                "ended_because": row.ended_because, "started_by": row.started_by, "started_s": row.started_s,
                "ended_s": row.ended_s, **self._loads(row.summary_json, "a run's summary"),
                "progress": self._loads(row.progress_json, "a run's progress")}

    def last_run(self) -> dict[str, Any] | None:
        r = S.production_runs.c
        with self._read() as conn:
            row = conn.execute(sa.select(r.id).where(r.cell_id == self.cell_id).order_by(r.id.desc()).limit(1)).first()
        return None if row is None else self.get_run(int(row[0]))

    def unended_runs(self) -> list[dict[str, Any]]:
        """The runs stored as not ended (at a start: the service died while they ran), oldest first."""
        r = S.production_runs.c
        with self._read() as conn:
            ids = conn.execute(sa.select(r.id).where(r.cell_id == self.cell_id, r.state.not_in(ENDED_STATES))
                               .order_by(r.id)).scalars().all()
        return [self.get_run(int(i)) for i in ids]

    def totals(self, exclude_run_id: int | None = None) -> dict[str, int]:
        """Every stored run's counters summed (all runs of the cell but ``exclude_run_id``)."""
        r = S.production_runs.c
        with self._read() as conn:
            rows = conn.execute(sa.select(r.id, r.summary_json).where(r.cell_id == self.cell_id)).all()
        out: dict[str, int] = {}
        for run_id, summary in rows:
            if run_id == exclude_run_id:
                continue
            for key, value in (self._loads(summary, "a run's summary").get("counters") or {}).items():
                out[key] = out.get(key, 0) + int(value)
        return out

    # -- cycles ------------------------------------------------------------------------------------
    def add_cycle(self, run_id: int, record: dict[str, Any], placed: tuple[int, int] | None = None) -> None:
        """Store a cycle's record; ``placed`` (recipe id, slot): the record of the part let go in that slot,
        which resolves the run's claim of it in the same transaction (a kill leaves both or neither)."""
        with self._write() as conn:
            conn.execute(S.production_cycles.insert().values(
                cell_id=self.cell_id, run_id=run_id, n=int(record["n"]), t=float(record["t"]),
                result=str(record["result"]), record_json=json.dumps(record, allow_nan=False)))
            if placed is not None:
                c = S.slot_claims.c
                conn.execute(S.slot_claims.delete().where(c.cell_id == self.cell_id, c.recipe_id == placed[0],
                                                          c.slot == placed[1], c.run_id == run_id))

    def cycles(self, run_id: int) -> list[dict[str, Any]]:
        """The run's cycle records, oldest first."""
        c = S.production_cycles.c
        with self._read() as conn:
            rows = conn.execute(sa.select(c.record_json).where(c.cell_id == self.cell_id, c.run_id == run_id)
                                .order_by(c.n)).all()
        return [self._loads(r[0], "a cycle record") for r in rows]

    def last_cycle(self, run_id: int) -> dict[str, Any] | None:
        c = S.production_cycles.c
        with self._read() as conn:
            row = conn.execute(sa.select(c.record_json).where(c.cell_id == self.cell_id, c.run_id == run_id)
                               .order_by(c.n.desc()).limit(1)).first()
        return None if row is None else self._loads(row[0], "a cycle record")
