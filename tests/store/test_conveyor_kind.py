"""A store made before the ``conveyor`` calibration kind takes one after its next start (schema 2 kept)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from cellctl.store import Store


def test_a_store_with_the_old_kind_check_stores_a_conveyor_calibration_after_a_restart(tmp_path: Path) -> None:
    db = tmp_path / "old.db"
    Store(f"sqlite:///{db}", "cell").save_calibration("npoint", "cam0", "robot0", {"H": 1}, {}, "eng")
    con = sqlite3.connect(db)  # the table as a store before conveyor tracking made it
    sql = con.execute("SELECT sql FROM sqlite_master WHERE name = 'calibrations'").fetchone()[0]
    con.execute("PRAGMA writable_schema = ON")
    con.execute("UPDATE sqlite_master SET sql = ? WHERE name = 'calibrations'",
                (sql.replace(", 'conveyor')", ")"),))
    con.execute(f"PRAGMA schema_version = {con.execute('PRAGMA schema_version').fetchone()[0] + 1}")
    con.commit()
    con.close()
    con = sqlite3.connect(db)
    try:
        con.execute("INSERT INTO calibrations (cell_id, kind, camera_id, robot_id, version, result_json, inputs_json,"
                    " sha256, tool_version, creator, note, created_s) VALUES ('c', 'conveyor', 'b', 'r', 1, '{}',"
                    " '{}', '', '', '', '', 0)")
        refused = False
    except sqlite3.IntegrityError:
        refused = True
    con.close()
    assert refused, "the old check should refuse the conveyor kind"
    store = Store(f"sqlite:///{db}", "cell")
    rec = store.save_calibration("conveyor", "belt0", "robot0", {"ticks_per_m": 10000.0}, {}, "eng")
    assert rec.kind == "conveyor" and store.list_calibrations("npoint")[0].camera_id == "cam0"
    assert store.get_calibration(rec.id).result["ticks_per_m"] == 10000.0
