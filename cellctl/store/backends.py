"""Engines for the two backends, chosen by URL: SQLite (embedded) and PostgreSQL (plant-wide).

SQLite: WAL mode, ``synchronous=FULL``, ``foreign_keys=ON`` and a busy timeout on every
connection; SQLAlchemy's pysqlite driver is switched to explicit transactions (the documented
recipe) so that a write transaction starts with ``BEGIN IMMEDIATE`` — writers queue on the
database lock up front instead of failing half-way on a lock upgrade, readers get a consistent
snapshot with a deferred ``BEGIN`` and never block writers.

PostgreSQL (psycopg 3): a write transaction first takes a transaction-scoped advisory lock keyed
by the cell id, so version numbers and the active pointer of one cell are assigned by one writer
at a time while other cells write in parallel.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sqlite3
from pathlib import Path
from typing import Any, Literal

import sqlalchemy as sa

from cellctl.store.errors import InvalidInput
from cellctl.store.files import create_private, private_dir, tighten

Backend = Literal["sqlite", "postgresql"]

WRITE_OPTION = "cellctl_write"
"""Execution option on a connection whose transaction will write (``BEGIN IMMEDIATE`` on SQLite)."""

SQLITE_BUSY_TIMEOUT_S = 30.0


def parse_url(url: str | sa.URL) -> sa.URL:
    """The URL as SQLAlchemy's, with ``postgresql://`` meaning psycopg 3; refuses other backends."""
    try:
        u = sa.make_url(url)
    except sa.exc.ArgumentError:
        raise InvalidInput(f"store url {str(url)!r} is not a database URL; use "
                           "postgresql+psycopg://user@host:port/dbname or sqlite:////path/to/file.db") from None
    backend = u.get_backend_name()
    if backend == "postgresql":
        if u.drivername == "postgresql":
            u = u.set(drivername="postgresql+psycopg")
        elif u.get_driver_name() != "psycopg":
            raise InvalidInput(f"store url: driver {u.get_driver_name()!r} is not supported; "
                               "use postgresql+psycopg://")
        if not u.database:
            raise InvalidInput("store url: name the database, e.g. postgresql+psycopg://user@127.0.0.1:5432/cellctl")
        if importlib.util.find_spec("psycopg") is None:
            raise InvalidInput("store url: a PostgreSQL store needs its driver, which is not installed: "
                               "pip install 'cellctl[postgres]' (deploy/install.sh --postgres)")
    elif backend == "sqlite":
        if u.get_driver_name() != "pysqlite":
            raise InvalidInput(f"store url: driver {u.get_driver_name()!r} is not supported; use sqlite:///")
        if not u.database or u.database == ":memory:":
            raise InvalidInput("store url: an in-memory SQLite store cannot be shared between threads; "
                               "give a file, e.g. sqlite:////var/lib/cellctl/cell.db")
    else:
        raise InvalidInput(f"store url: backend {backend!r} is not supported; use SQLite or PostgreSQL")
    return u


def sqlite_url(path: str | Path) -> sa.URL:
    return sa.URL.create("sqlite+pysqlite", database=str(Path(path).expanduser().absolute()))


def backend_of(url: sa.URL) -> Backend:
    return "postgresql" if url.get_backend_name() == "postgresql" else "sqlite"


def advisory_key(cell_id: str) -> int:
    """A signed 64-bit key for ``pg_advisory_xact_lock`` derived from the cell id."""
    return int.from_bytes(hashlib.sha256(b"cellctl-store:" + cell_id.encode()).digest()[:8], "big", signed=True)


def make_engine(url: sa.URL) -> sa.Engine:
    """An engine for ``url`` (already checked by :func:`parse_url`) with the backend's settings."""
    if backend_of(url) == "sqlite":
        return _sqlite_engine(url)
    return sa.create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=10)


def _sqlite_engine(url: sa.URL) -> sa.Engine:
    path = Path(str(url.database))
    try:
        private_dir(path.parent)
        if not create_private(path):  # a new store is 0600 (and so are its -wal/-shm: SQLite copies the mode)
            tighten(path)
    except OSError as exc:
        raise InvalidInput(f"store: cannot create {path} ({exc.strerror}); "
                           "set store.path in cell.yaml to a writable place") from None
    engine = sa.create_engine(
        url,
        connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S, "check_same_thread": False},
        pool_size=5, max_overflow=10,
    )

    @sa.event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: sqlite3.Connection, _record: Any) -> None:
        dbapi_conn.isolation_level = None  # transactions are begun explicitly below
        cur = dbapi_conn.cursor()
        try:
            cur.execute(f"PRAGMA busy_timeout={int(SQLITE_BUSY_TIMEOUT_S * 1000)}")
            mode = cur.execute("PRAGMA journal_mode=WAL").fetchone()
            if mode is None or str(mode[0]).lower() != "wal":
                raise InvalidInput(f"store: {path} cannot be put in WAL mode (got {mode}); "
                                   "put it on a local file system")
            cur.execute("PRAGMA synchronous=FULL")
            cur.execute("PRAGMA foreign_keys=ON")
        finally:
            cur.close()

    @sa.event.listens_for(engine, "begin")
    def _on_begin(conn: sa.Connection) -> None:
        write = conn.get_execution_options().get(WRITE_OPTION, False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

    return engine
