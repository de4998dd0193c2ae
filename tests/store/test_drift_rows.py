"""Drift checks in the store: written and read back per camera and calibration, carried by a backup
and its restore (renumbered with their calibration), and a backup of schema 2 restores without them."""

from __future__ import annotations

import json
from pathlib import Path

from cellctl.store import Store
from cellctl.store import schema as S
from cellctl.store.backup import backup, restore


def _rec(t: float, mm: float, state: str = "baseline") -> dict[str, object]:
    return {"t": t, "drift_px": mm * 2.8, "drift_mm": mm, "drift_deg": 0.001, "state": state, "rule": None}


def test_checks_are_kept_per_camera_and_calibration(store: Store) -> None:
    cal = store.save_calibration("handeye", "cam0", "robot0", {"setup": "eye-to-hand"}, {}, creator="t")
    for k in range(5):
        store.add_drift_check("cam0", cal.id, _rec(100.0 + k, 0.01 * k))
    store.add_drift_check("cam0", None, _rec(200.0, 0.5, "alarm"))
    store.add_drift_check("cam1", cal.id, _rec(300.0, 0.2))
    rows = store.drift_checks("cam0")
    assert [r["t"] for r in rows] == [100.0, 101.0, 102.0, 103.0, 104.0, 200.0]  # oldest first
    assert [r["drift_mm"] for r in store.drift_checks("cam0", limit=2)] == [0.04, 0.5]  # the last two
    assert len(store.drift_checks("cam0", calibration_id=cal.id)) == 5
    assert rows[-1]["state"] == "alarm" and rows[0]["calibration_id"] == cal.id
    assert [r["t"] for r in store.drift_checks("cam1")] == [300.0]


def test_a_backup_carries_the_checks_and_one_of_schema_2_restores_without(tmp_path: Path, store: Store) -> None:
    cal = store.save_calibration("handeye", "cam0", "robot0", {"setup": "eye-to-hand"}, {}, creator="t")
    store.add_drift_check("cam0", cal.id, _rec(1.0, 0.02))
    store.add_drift_check("cam0", cal.id, _rec(2.0, 0.4, "alarm"))
    out = tmp_path / "b.json"
    backup(store, out, "json")
    dump = json.loads(out.read_text())
    assert dump["schema_version"] == S.SCHEMA_VERSION == 3 and len(dump["tables"]["drift_checks"]["rows"]) == 2
    result = restore(store, out, "maint", force=True)
    assert result["counts"]["drift_checks"] == 2
    rows = store.drift_checks("cam0")
    assert [(r["drift_mm"], r["state"]) for r in rows] == [(0.02, "baseline"), (0.4, "alarm")]
    assert {r["calibration_id"] for r in rows} == {store.list_calibrations("handeye")[0].id}
    dump["schema_version"] = 2
    del dump["tables"]["drift_checks"]
    old = tmp_path / "v2.json"
    old.write_text(json.dumps(dump))
    restore(store, old, "maint", force=True)
    assert store.drift_checks("cam0") == []
