"""The store of one cell: its connections and transactions, its schema (created, migrated) and the
audit log; the rows of each job are mixed in from their own module: versioned calibrations with
their inputs and the active pointer with its history (``calibrations.py``), recipes
(``recipes.py``), the robots' latches (``latches.py``), production's runs, cycles and slots
(``production.py``) and the drift checks (``drift.py``) — one data-access layer over SQLite or
PostgreSQL.

Every write is one database transaction that also appends its audit entry, so a process killed at
any moment leaves either the whole act (record + audit) or nothing. A :class:`Store` is safe to
share between threads: each call checks a connection out of the engine's pool for its duration.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import sqlalchemy as sa

from cellctl.store import schema as S
from cellctl.store.backends import WRITE_OPTION, Backend, advisory_key, backend_of, make_engine, parse_url
from cellctl.store.calibrations import CalibrationRows
from cellctl.store.drift import DriftRows
from cellctl.store.errors import InvalidInput, StoreDamaged, StoreError, StoreFormatError, StoreUnavailable
from cellctl.store.integrity import recovery_hint, store_error
from cellctl.store.latches import LatchRows
from cellctl.store.production import ProductionRows
from cellctl.store.recipes import RecipeRows
from cellctl.store.records import AuditEntry
from cellctl.store.values import check_text, to_json_text

log = logging.getLogger(__name__)

MAX_AUDIT_LIMIT = 10_000


class Store(CalibrationRows, LatchRows, ProductionRows, RecipeRows, DriftRows):
    """One cell's store. Open it with :func:`cellctl.store.open_store` or ``Store(url, cell_id)``.

    ``url`` is a SQLAlchemy URL: ``sqlite:////abs/path.db`` or
    ``postgresql+psycopg://user@host:port/dbname``. The tables are created when missing; a store
    written by a newer cellctl is refused with :class:`StoreFormatError`. A damaged or unreachable
    store raises :class:`StoreUnavailable` (:class:`StoreDamaged`: ``recovery`` says what to do) and
    :attr:`problem` keeps saying so (see integrity.py).
    """

    def __init__(self, url: str | sa.URL, cell_id: str, recovery: str | None = None) -> None:
        if not cell_id:
            raise InvalidInput("store: cell_id must not be empty")
        self.url = parse_url(url)
        self.cell_id = cell_id
        self.recovery = recovery if recovery is not None else recovery_hint(None)  # the environment now, not at import
        self._damaged: str | None = None  # kept until the process ends: only a restore mends it
        self._unavailable: str | None = None  # cleared by the next call that succeeds
        self.backend: Backend = backend_of(self.url)
        self._engine = make_engine(self.url)
        try:
            self._create_schema()
        except BaseException:
            self._engine.dispose()
            raise

    # ------------------------------------------------------------------ plumbing

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the connections; safe to call twice."""
        self._engine.dispose()

    @property
    def engine(self) -> sa.Engine:
        return self._engine

    def describe(self) -> str:
        """The URL without its password (for logs and CLI output)."""
        return self.url.render_as_string(hide_password=True)

    @property
    def problem(self) -> str | None:
        """Why the store cannot be used, as last met by a call (damage stays reported); None: fine."""
        return self._damaged or self._unavailable

    def _failed(self, exc: sa.exc.DBAPIError) -> StoreError:
        err = store_error(exc, self.describe(), self.backend, self.recovery)
        return self._note(err)

    def _note(self, err: StoreError) -> StoreError:
        if isinstance(err, StoreDamaged):
            self._damaged = self._damaged or str(err)
        elif isinstance(err, StoreUnavailable):
            self._unavailable = str(err)
        return err

    def _loads(self, text: str, what: str) -> Any:
        """Stored JSON text parsed; text that does not parse means the storage was damaged."""
        try:
            return json.loads(text)
        except ValueError as exc:
            raise self._note(StoreDamaged(f"store {self.describe()} is damaged ({what} is not JSON: {exc}); "
                                          f"{self.recovery}")) from None

    @contextmanager
    def _read(self) -> Iterator[sa.Connection]:
        try:
            with self._engine.connect() as conn, conn.begin():
                yield conn
        except sa.exc.IntegrityError:
            raise
        except sa.exc.DBAPIError as exc:  # unreachable server, locked/damaged file, not a database ...
            raise self._failed(exc) from exc
        self._unavailable = None

    @contextmanager
    def _write(self) -> Iterator[sa.Connection]:
        """One write transaction: committed when the block ends, rolled back on any exception."""
        try:
            with self._engine.connect() as conn:
                conn.execution_options(**{WRITE_OPTION: True})
                with conn.begin():
                    if self.backend == "postgresql":
                        conn.execute(sa.select(sa.func.pg_advisory_xact_lock(advisory_key(self.cell_id))))
                    yield conn
        except sa.exc.IntegrityError:
            raise
        except sa.exc.DBAPIError as exc:
            raise self._failed(exc) from exc
        self._unavailable = None

    def _create_schema(self) -> None:
        with self._write() as conn:
            if self.backend == "postgresql":  # one creator at a time across processes
                conn.execute(sa.select(sa.func.pg_advisory_xact_lock(advisory_key("\0schema"))))
            inspector = sa.inspect(conn)
            existing = set(inspector.get_table_names())
            ours = {t.name for t in S.metadata.sorted_tables}
            if existing & (ours - {S.meta.name}) and S.meta.name not in existing:
                raise StoreFormatError(f"store {self.describe()}: has tables named like cellctl's but no "
                                       f"{S.meta.name} table; it is not a cellctl store: "
                                       "point store.url/path elsewhere")
            if ours - existing:  # a current store has every table: nothing to create, nothing to ask per table
                S.metadata.create_all(conn)
            rows = {str(r[0]): str(r[1]) for r in conn.execute(sa.select(S.meta.c.key, S.meta.c.value))}
            if not rows:
                conn.execute(S.meta.insert(), [{"key": "format", "value": S.STORE_MARKER},
                                               {"key": "schema_version", "value": str(S.SCHEMA_VERSION)}])
                return
            if rows.get("format") != S.STORE_MARKER:
                raise StoreFormatError(f"store {self.describe()}: not a cellctl store (format={rows.get('format')!r})")
            version = int(rows.get("schema_version", "0"))
            if version > S.SCHEMA_VERSION:
                raise StoreFormatError(f"store {self.describe()} has schema version {version}, newer than this "
                                       f"cellctl supports ({S.SCHEMA_VERSION}); upgrade cellctl")
            if version < S.SCHEMA_VERSION:
                self._migrate(conn, version)
            self._widen_kind_check(conn)

    def _widen_kind_check(self, conn: sa.Connection) -> None:
        """A store made before the ``conveyor`` calibration kind: its calibrations table gets today's check
        (SQLite: the table is rebuilt with its rows; PostgreSQL: the constraint is replaced)."""
        if self.backend == "postgresql":
            found = conn.exec_driver_sql("SELECT pg_get_constraintdef(oid) FROM pg_constraint WHERE conname = "
                                         "'ck_calibration_kind'").scalar()
            if found is not None and "conveyor" not in str(found):
                conn.exec_driver_sql("ALTER TABLE calibrations DROP CONSTRAINT ck_calibration_kind")
                conn.exec_driver_sql(f"ALTER TABLE calibrations ADD CONSTRAINT ck_calibration_kind CHECK "
                                     f"({S.KIND_CHECK})")
            return
        sql = conn.exec_driver_sql("SELECT sql FROM sqlite_master WHERE type = 'table' AND name = 'calibrations'"
                                   ).scalar()
        if sql is None or "conveyor" in str(sql):
            return
        new_sql = str(sql).replace("'npoint')", "'npoint', 'conveyor')")
        if new_sql == sql:
            log.warning("store %s: the calibrations table's kind check is not the one expected; left as it is",
                        self.describe())
            return
        # SQLite cannot alter a check: the table's definition is rewritten in place (same columns, the
        # wider check; PRAGMA writable_schema as SQLite's docs describe for exactly this change).
        conn.exec_driver_sql("PRAGMA writable_schema = ON")
        conn.exec_driver_sql("UPDATE sqlite_master SET sql = ? WHERE type = 'table' AND name = 'calibrations'",
                             (new_sql,))
        version = conn.exec_driver_sql("PRAGMA schema_version").scalar()
        conn.exec_driver_sql(f"PRAGMA schema_version = {int(version or 0) + 1}")
        conn.exec_driver_sql("PRAGMA writable_schema = OFF")

    def _migrate(self, conn: sa.Connection, version: int) -> None:
        """Bring a store of an older schema ``version`` to this one, in the schema's transaction (the
        new tables were just created; an older table gets its new columns, its rows the default)."""
        for since, added in sorted(S.ADDED_COLUMNS.items()):
            if since <= version:
                continue
            for table, column, default in added:
                have = {c["name"] for c in sa.inspect(conn).get_columns(table.name)}
                if column.name not in have:
                    kind = column.type.compile(dialect=conn.dialect)
                    conn.exec_driver_sql(f"ALTER TABLE {table.name} ADD COLUMN {column.name} {kind} "
                                         f"NOT NULL DEFAULT {default}")
        conn.execute(sa.update(S.meta).where(S.meta.c.key == "schema_version").values(value=str(S.SCHEMA_VERSION)))

    def _audit(self, conn: sa.Connection, who: str, action: str, target: str, detail: dict[str, Any],
               result: str, at_s: float | None = None) -> None:
        conn.execute(S.audit.insert().values(
            cell_id=self.cell_id, at_s=time.time() if at_s is None else at_s, who=who, action=action,
            target=target, detail_json=to_json_text(detail, "audit detail"), result=result))

    # ------------------------------------------------------------------ audit

    def audit(self, who: str, action: str, target: str, detail: dict[str, Any], result: str) -> None:
        """Log one act (a motion, a calibration change, a restore ...) with its result."""
        check_text(who, "who")
        check_text(action, "action")
        if not isinstance(detail, dict):
            raise InvalidInput("audit: detail must be a dict")
        with self._write() as conn:
            self._audit(conn, who, action, target, detail, result)

    def audit_log(self, limit: int = 100, action: str | None = None) -> list[AuditEntry]:
        """The newest ``limit`` entries (newest first), optionally only one ``action``."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_AUDIT_LIMIT:
            raise InvalidInput(f"audit_log: limit must be an integer in 1..{MAX_AUDIT_LIMIT}, got {limit!r}")
        t = S.audit.c
        q = sa.select(S.audit).where(t.cell_id == self.cell_id)
        if action is not None:
            q = q.where(t.action == action)
        with self._read() as conn:
            rows = conn.execute(q.order_by(t.id.desc()).limit(limit)).all()
        return [AuditEntry(id=r.id, cell_id=r.cell_id, at_s=r.at_s, who=r.who, action=r.action, target=r.target,
                           detail=self._loads(r.detail_json, "an audit entry"), result=r.result) for r in rows]

    # ------------------------------------------------------------------ whole-store

    def counts(self) -> dict[str, int]:
        """Rows of this cell per table."""
        with self._read() as conn:
            return {t.name: int(conn.execute(sa.select(sa.func.count()).select_from(t).where(
                t.c.cell_id == self.cell_id)).scalar_one()) for t in S.CELL_TABLES}

    def is_empty(self) -> bool:
        return not any(self.counts().values())
