"""Production's rows in the store's one schema: slot claims (claimed, in doubt, confirmed), the runs an
older store kept in tables of their own migrated in place, and backups of an older schema restored."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import sqlalchemy as sa

from cellctl.store import NotFound, Store
from cellctl.store import schema as S
from cellctl.store.backup import backup, restore
from cellctl.store.production import SlotTaken

V1_PRODUCTION_DDL = (
    "CREATE TABLE production_slots (cell_id VARCHAR(128) NOT NULL, recipe_id INTEGER NOT NULL, "
    "next_slot INTEGER NOT NULL, who VARCHAR(256) NOT NULL, at_s DOUBLE PRECISION NOT NULL, "
    "PRIMARY KEY (cell_id, recipe_id))",
    "CREATE TABLE production_runs (id {serial} PRIMARY KEY, cell_id VARCHAR(128) NOT NULL, recipe_id INTEGER NOT NULL, "
    "robot_id VARCHAR(128) NOT NULL, started_by VARCHAR(256) NOT NULL, started_s DOUBLE PRECISION NOT NULL, "
    "ended_s DOUBLE PRECISION, state VARCHAR(16) NOT NULL, ended_because VARCHAR(32), summary_json TEXT NOT NULL)",
    "CREATE TABLE production_cycles (id {serial} PRIMARY KEY, cell_id VARCHAR(128) NOT NULL, run_id INTEGER NOT NULL, "
    "n INTEGER NOT NULL, t DOUBLE PRECISION NOT NULL, result VARCHAR(32) NOT NULL, record_json TEXT NOT NULL, "
    "CONSTRAINT uq_production_cycle UNIQUE (cell_id, run_id, n))",
)
"""The production tables as cellctl 1 created them on first use, beside a schema-version-1 store."""


def test_a_claimed_slot_is_skipped_until_confirmed_and_the_confirmation_is_audited(store: Store) -> None:
    assert store.free_slot(1) == 0
    store.claim_slot(1, 0, run_id=5, n=1, detail={"pick_pose": None})
    assert store.next_slot(1) == 1 and store.free_slot(1) == 1  # the counter moved past it with the claim
    with pytest.raises(SlotTaken):
        store.claim_slot(1, 0, run_id=6, n=1, detail={})
    store.placed_in_slot(1, 0, run_id=5)
    store.claim_slot(1, 1, run_id=5, n=2, detail={})
    store.slot_in_doubt(1, 1, run_id=5, detail={"phase": "over_slot", "held": True})
    store.claim_slot(1, 2, run_id=5, n=3, detail={})  # still 'claimed': the service died
    assert [d["slot"] for d in store.slots_in_doubt()] == [1]
    at_start = store.claims_in_doubt_at_start("the service ended")
    assert [(d["slot"], d["in_doubt_because"]) for d in at_start] == [(2, "the service ended")]
    assert [(d["slot"], d.get("phase")) for d in store.slots_in_doubt(1)] == [(1, "over_slot"), (2, None)]
    # Someone sets the counter back over them: they are still skipped.
    store.set_next_slot(1, 1, "eng")
    assert store.free_slot(1) == 3
    store.set_next_slot(1, 3, "eng")
    with pytest.raises(NotFound):
        store.confirm_slot(1, 0, True, "eng")  # not in doubt
    out = store.confirm_slot(1, 2, False, "eng")  # empty, and the counter just past it: back to it
    assert out["next_slot"] == 2 and store.free_slot(1) == 2
    out = store.confirm_slot(1, 1, True, "eng")
    assert out["occupied"] is True and store.slots_in_doubt() == [] and store.free_slot(1) == 2
    entries = store.audit_log(action="production.slot_confirm")
    assert [(e.detail["slot"], e.detail["occupied"], e.who) for e in entries] == [(1, True, "eng"), (2, False, "eng")]


def _v1_store(url: str, cell_id: str) -> None:
    """A store as cellctl with schema version 1 left it: its tables, and production's on the side."""
    engine = sa.create_engine(url.replace("postgresql://", "postgresql+psycopg://", 1))
    v1 = [t for t in S.metadata.sorted_tables if t.name not in S.TABLES_SINCE]
    serial = "SERIAL" if engine.dialect.name == "postgresql" else "INTEGER"
    with engine.begin() as conn:
        S.metadata.create_all(conn, tables=v1)
        present = {r[0] for r in conn.execute(sa.select(S.meta.c.key))}
        if not present:
            conn.execute(S.meta.insert(), [{"key": "format", "value": S.STORE_MARKER},
                                           {"key": "schema_version", "value": "1"}])
        if "production_runs" not in sa.inspect(conn).get_table_names():
            for ddl in V1_PRODUCTION_DDL:
                conn.exec_driver_sql(ddl.format(serial=serial))
        conn.exec_driver_sql(
            "INSERT INTO production_runs (cell_id, recipe_id, robot_id, started_by, started_s, ended_s, state, "
            f"ended_because, summary_json) VALUES ('{cell_id}', 1, 'robot0', 'eng', 1.0, 2.0, 'complete', "
            """'count_reached', '{"counters": {"placed": 4}}')""")
        conn.exec_driver_sql(f"INSERT INTO production_slots VALUES ('{cell_id}', 1, 4, 'run', 2.0)")
        run_id = conn.exec_driver_sql(f"SELECT max(id) FROM production_runs WHERE cell_id = '{cell_id}'").scalar()
        conn.exec_driver_sql(f"INSERT INTO production_cycles (cell_id, run_id, n, t, result, record_json) VALUES "
                             f"""('{cell_id}', {run_id}, 1, 1.5, 'placed', '{{"n": 1, "slot": 3}}')""")
    engine.dispose()


_fresh = iter(range(1_000_000))


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_store_of_schema_1_with_production_tables_opens_migrated_and_keeps_its_rows(
        backend: str, tmp_path: Path, request: pytest.FixtureRequest, cell_id: str) -> None:
    if backend == "sqlite":
        store_url = f"sqlite:///{tmp_path / 'v1.db'}"
    else:  # a database of its own: the shared one is at version 2 already
        store_url = request.getfixturevalue("postgres").create_database(f"v1_store_{next(_fresh)}")
    _v1_store(store_url, cell_id)
    with Store(store_url, cell_id) as store:
        with store.engine.connect() as conn:
            version = conn.execute(sa.select(S.meta.c.value).where(S.meta.c.key == "schema_version")).scalar()
        assert version == str(S.SCHEMA_VERSION) == "3"  # 3: drift checks (issue 40)
        last = store.last_run()
        assert last is not None and last["state"] == "complete" and last["counters"] == {"placed": 4}
        assert last["progress"] == {}  # the column added, its default
        assert store.next_slot(1) == 4 and store.cycles(last["run_id"]) == [{"n": 1, "slot": 3}]
        store.claim_slot(1, 4, last["run_id"], 2, {})  # the new table is there
    with Store(store_url, cell_id) as again:  # opened twice: migrated once
        assert again.free_slot(1) == 5


def test_a_backup_of_schema_1_restores_with_production_empty(tmp_path: Path, store: Store) -> None:
    store.save_recipe(1, "bolt", {"model": "m"}, "alice")
    out = tmp_path / "v2.json"
    backup(store, out, "json")
    dump = json.loads(out.read_text())
    dump["schema_version"] = 1
    for name in S.TABLES_SINCE:
        del dump["tables"][name]
    old = tmp_path / "v1.json"
    old.write_text(json.dumps(dump))
    result = restore(store, old, "maint", force=True)
    assert result["counts"] == {"recipes": 1, "audit": 1}
    assert store.get_recipe(1).name == "bolt" and store.last_run() is None and store.next_slot(1) == 0
