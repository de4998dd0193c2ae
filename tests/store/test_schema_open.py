"""Opening a store cheaply (``Store._create_schema``): a current store asks for nothing it has, a missing table
is made again; a new store's schema is the one create_all makes."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from cellctl.store import Store
from cellctl.store import schema as S
from cellctl.store.backends import make_engine, sqlite_url


def _master(db: Path) -> list[tuple[Any, ...]]:
    """The database's schema as SQLite keeps it (every table, index and trigger with its SQL)."""
    engine = make_engine(sqlite_url(db))
    try:
        with engine.connect() as conn:
            return [tuple(r) for r in conn.exec_driver_sql(
                "SELECT type, name, tbl_name, sql FROM sqlite_master ORDER BY type, name")]
    finally:
        engine.dispose()


@contextmanager
def _statements() -> Iterator[list[str]]:
    """Every statement any engine of this process sends while the block runs."""
    sent: list[str] = []

    def record(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        sent.append(statement)

    sa.event.listen(sa.Engine, "before_cursor_execute", record)
    try:
        yield sent
    finally:
        sa.event.remove(sa.Engine, "before_cursor_execute", record)


def test_a_new_store_has_the_schema_create_all_makes(tmp_path: Path) -> None:
    for i in range(2):  # two new stores in one process
        Store(sqlite_url(tmp_path / f"new{i}.db"), "cell").close()
    engine = make_engine(sqlite_url(tmp_path / "reference.db"))
    with engine.begin() as conn:
        S.metadata.create_all(conn)
    engine.dispose()
    reference = _master(tmp_path / "reference.db")
    assert len([r for r in reference if r[0] == "table"]) == len(S.metadata.tables)
    assert any(r[0] == "trigger" for r in reference) and any(r[0] == "index" for r in reference)
    assert _master(tmp_path / "new0.db") == reference
    assert _master(tmp_path / "new1.db") == reference


def test_a_current_store_opens_without_ddl_and_a_missing_table_is_made_again(tmp_path: Path) -> None:
    db = tmp_path / "store.db"
    Store(sqlite_url(db), "cell").close()
    made = _master(db)
    with _statements() as sent:
        Store(sqlite_url(db), "cell").close()
    assert sent and not [s for s in sent if s.lstrip().upper().startswith(("CREATE", "ALTER", "DROP"))
                         or "table_info" in s.lower()]  # create_all asks for each table with table_info
    engine = make_engine(sqlite_url(db))
    with engine.begin() as conn:
        conn.exec_driver_sql("DROP TABLE drift_checks")
    engine.dispose()
    with _statements() as sent:
        Store(sqlite_url(db), "cell").close()
    assert any("CREATE TABLE drift_checks" in s for s in sent)
    assert _master(db) == made
