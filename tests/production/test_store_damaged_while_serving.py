"""A store damaged while the service serves (issue 34): ``GET /production`` and a run's cycles answer 503
``store_unavailable`` naming the restore command, never a 500; the service writes nothing over what
is left; and the command it names brings every production record back (runs, cycles, the slot
counter, the slots in doubt).

Two damages: a table of the schema dropped behind the service's back (SQLite "no such table"), and a
page of the runs' table overwritten (SQLite "malformed"). The app runs in this process.
"""

from __future__ import annotations

import random
import sqlite3
from pathlib import Path
from typing import Any

import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text, load_config
from cellctl.store import open_store
from tests.support.app import in_process_cell


def damage(db: Path, how: str) -> None:
    """Damage the store under the running service (its connections stay open)."""
    conn = sqlite3.connect(db)
    try:
        if how == "dropped":
            conn.execute("DROP TABLE production_runs")
            conn.commit()
            return
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        (root,) = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'production_runs'").fetchone()
        (page_size,) = conn.execute("PRAGMA page_size").fetchone()
    finally:
        conn.close()
    with db.open("r+b") as f:  # what a failing disk or a stray write does
        f.seek((root - 1) * page_size)
        f.write(random.Random(7).randbytes(page_size))


def production_records(config: Path) -> dict[str, Any]:
    with open_store(load_config(config)) as store:
        last = store.last_run()
        assert last is not None
        run_id = int(last["run_id"])
        return {"run": (last["state"], last["ended_because"], last["counters"]),
                "cycles": [(c["n"], c["result"], c["slot"]) for c in store.cycles(run_id)],
                "next_slot": store.next_slot(1),
                "in_doubt": [(d["recipe_id"], d["slot"]) for d in store.slots_in_doubt()]}


@pytest.mark.parametrize("how", ["dropped", "corrupted"])
def test_a_store_damaged_while_serving_answers_503_and_the_named_restore_brings_the_records_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str) -> None:
    db = tmp_path / "store" / "cell.db"
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(db), "backup_dir": str(tmp_path / "backups")}
    config = tmp_path / "cell.yaml"
    config.write_text(yaml.safe_dump(data))
    with open_store(load_config(config)) as store:
        run_id = store.new_run(1, "robot0", "eng")
        for n, slot in ((1, 0), (2, 1)):
            store.claim_slot(1, slot, run_id, n, {})
            store.add_cycle(run_id, {"n": n, "t": float(n), "result": "placed", "slot": slot}, placed=(1, slot))
            store.placed_in_slot(1, slot, run_id)
        store.claim_slot(1, 2, run_id, 3, {"phase": "over_slot"})
        store.slot_in_doubt(1, 2, run_id, {"phase": "over_slot"})
        store.add_cycle(run_id, {"n": 3, "t": 3.0, "result": "stopped", "slot": 2, "slot_state": "in_doubt"})
        store.update_run(run_id, "stopped", "stopped", {"counters": {"placed": 2}}, ended=True)
    before = production_records(config)
    assert before["cycles"] == [(1, "placed", 0), (2, "placed", 1), (3, "stopped", 2)]
    assert before["next_slot"] == 3 and before["in_doubt"] == [(1, 2)]
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))
    assert main(["store", "backup", "--config", str(config)]) == 0

    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        assert http.get("/production").json()["run_id"] == run_id
        damage(db, how)
        for path in ("/production", f"/production/runs/{run_id}/cycles"):
            r = http.get(path)
            assert r.status_code == 503, (path, r.status_code, r.text)
            error = r.json()["error"]
            assert error["code"] == "store_unavailable" and "is damaged" in error["message"], error
            assert f"cellctl store restore --config {config} --latest --force" in error["message"], error
        assert http.get("/health").json()["store"]["available"] is False

    # The rows the damage did not reach are as they were (the service did not drop or rewrite them).
    with sqlite3.connect(db) as conn:
        cycles = conn.execute("SELECT n FROM production_cycles WHERE run_id = ? ORDER BY n", (run_id,)).fetchall()
    assert [n for (n,) in cycles] == [1, 2, 3]

    # The command the 503 names brings every production record back.
    assert main(["store", "restore", "--config", str(config), "--latest", "--force"]) == 0
    assert production_records(config) == before
