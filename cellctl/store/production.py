"""Production's stored state: the next free place slot per recipe, the runs, and every cycle's record.

Tables of their own (created on first use in the cell's store database, SQLite or PostgreSQL), so
that the slot counter survives a restart and a run's cycles can be read back and exported. Rows
carry ``cell_id`` like every table of the store.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import sqlalchemy as sa

from cellctl.store.backends import WRITE_OPTION
from cellctl.store.errors import NotFound, StoreError
from cellctl.store.integrity import DEFAULT_RECOVERY, store_error

metadata = sa.MetaData()

slots = sa.Table(
    "production_slots", metadata,
    sa.Column("cell_id", sa.String(128), primary_key=True),
    sa.Column("recipe_id", sa.Integer, primary_key=True),
    sa.Column("next_slot", sa.Integer, nullable=False),
    sa.Column("who", sa.String(256), nullable=False),
    sa.Column("at_s", sa.Double, nullable=False),
)

runs = sa.Table(
    "production_runs", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("recipe_id", sa.Integer, nullable=False),
    sa.Column("robot_id", sa.String(128), nullable=False),
    sa.Column("started_by", sa.String(256), nullable=False),
    sa.Column("started_s", sa.Double, nullable=False),
    sa.Column("ended_s", sa.Double, nullable=True),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("ended_because", sa.String(32), nullable=True),
    sa.Column("summary_json", sa.Text, nullable=False),
)

cycles = sa.Table(
    "production_cycles", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("run_id", sa.Integer, nullable=False),
    sa.Column("n", sa.Integer, nullable=False),
    sa.Column("t", sa.Double, nullable=False),
    sa.Column("result", sa.String(32), nullable=False),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.UniqueConstraint("cell_id", "run_id", "n", name="uq_production_cycle"),
)

sa.Index("ix_production_cycles_run", cycles.c.cell_id, cycles.c.run_id, cycles.c.n)


class ProductionStore:
    """Production rows of one cell in the cell's store (``cellctl.store.Store``)."""

    def __init__(self, engine: sa.Engine, cell_id: str) -> None:
        self._engine = engine
        self.cell_id = cell_id
        self._lock = threading.Lock()
        with self._write() as conn:
            metadata.create_all(conn)

    @contextmanager
    def _write(self) -> Iterator[sa.Connection]:
        try:
            with self._engine.connect() as conn:
                conn.execution_options(**{WRITE_OPTION: True})
                with conn.begin():
                    yield conn
        except sa.exc.DBAPIError as exc:
            raise self._failed(exc) from exc

    @contextmanager
    def _read(self) -> Iterator[sa.Connection]:
        try:
            with self._engine.connect() as conn, conn.begin():
                yield conn
        except sa.exc.DBAPIError as exc:
            raise self._failed(exc) from exc

    def _failed(self, exc: sa.exc.DBAPIError) -> StoreError:
        """The typed error of a database error: damaged or unavailable (503 ``store_unavailable``), as the store's."""
        url = self._engine.url
        where = f"{url.database} (production tables)" if url.database else "production tables"
        return store_error(exc, where, self._engine.dialect.name, DEFAULT_RECOVERY)

    # -- slots ------------------------------------------------------------------------------------
    def next_slot(self, recipe_id: int) -> int:
        """The recipe's next free place slot (0 when never set)."""
        with self._read() as conn:
            row = conn.execute(sa.select(slots.c.next_slot).where(
                slots.c.cell_id == self.cell_id, slots.c.recipe_id == recipe_id)).first()
        return 0 if row is None else int(row[0])

    def set_next_slot(self, recipe_id: int, next_slot: int, who: str) -> None:
        with self._lock, self._write() as conn:
            key = (slots.c.cell_id == self.cell_id) & (slots.c.recipe_id == recipe_id)
            values = {"next_slot": int(next_slot), "who": who, "at_s": time.time()}
            if conn.execute(sa.update(slots).where(key).values(**values)).rowcount == 0:
                conn.execute(slots.insert().values(cell_id=self.cell_id, recipe_id=recipe_id, **values))

    # -- runs -------------------------------------------------------------------------------------
    def new_run(self, recipe_id: int, robot_id: str, who: str) -> int:
        with self._write() as conn:
            result = conn.execute(runs.insert().values(
                cell_id=self.cell_id, recipe_id=recipe_id, robot_id=robot_id, started_by=who, started_s=time.time(),
                state="running", summary_json="{}"))
            key = result.inserted_primary_key
            assert key is not None
            return int(key[0])

    def update_run(self, run_id: int, state: str, ended_because: str | None, summary: dict[str, Any],
                   ended: bool = False) -> None:
        values: dict[str, Any] = {"state": state, "ended_because": ended_because,
                                  "summary_json": json.dumps(summary, allow_nan=False)}
        if ended:
            values["ended_s"] = time.time()
        with self._write() as conn:
            conn.execute(sa.update(runs).where(runs.c.id == run_id, runs.c.cell_id == self.cell_id).values(**values))

    def get_run(self, run_id: int) -> dict[str, Any]:
        with self._read() as conn:
            row = conn.execute(sa.select(runs).where(runs.c.id == run_id, runs.c.cell_id == self.cell_id)).first()
        if row is None:
            raise NotFound(f"no production run {run_id} in cell {self.cell_id!r}")
        return {"run_id": row.id, "recipe_id": row.recipe_id, "robot_id": row.robot_id, "state": row.state,
                "ended_because": row.ended_because, "started_by": row.started_by, "started_s": row.started_s,
                "ended_s": row.ended_s, **json.loads(row.summary_json)}

    def last_run(self) -> dict[str, Any] | None:
        with self._read() as conn:
            row = conn.execute(sa.select(runs.c.id).where(runs.c.cell_id == self.cell_id)
                               .order_by(runs.c.id.desc()).limit(1)).first()
        return None if row is None else self.get_run(int(row[0]))

    def totals(self, exclude_run_id: int | None = None) -> dict[str, int]:
        """Every stored run's counters summed (all runs of the cell but ``exclude_run_id``)."""
        with self._read() as conn:
            rows = conn.execute(sa.select(runs.c.id, runs.c.summary_json).where(runs.c.cell_id == self.cell_id)).all()
        out: dict[str, int] = {}
        for run_id, summary in rows:
            if run_id == exclude_run_id:
                continue
            for key, value in (json.loads(summary).get("counters") or {}).items():
                out[key] = out.get(key, 0) + int(value)
        return out

    # -- cycles -----------------------------------------------------------------------------------
    def add_cycle(self, run_id: int, record: dict[str, Any]) -> None:
        with self._write() as conn:
            conn.execute(cycles.insert().values(cell_id=self.cell_id, run_id=run_id, n=int(record["n"]),
                                                t=float(record["t"]), result=str(record["result"]),
                                                record_json=json.dumps(record, allow_nan=False)))

    def cycles(self, run_id: int) -> list[dict[str, Any]]:
        """The run's cycle records, oldest first."""
        with self._read() as conn:
            rows = conn.execute(sa.select(cycles.c.record_json).where(
                cycles.c.cell_id == self.cell_id, cycles.c.run_id == run_id).order_by(cycles.c.n)).all()
        return [json.loads(r[0]) for r in rows]
