"""Helpers shared by the store tests and the store CLI tests."""

from __future__ import annotations

import random
import sqlite3
from pathlib import Path
from typing import Any

from cellctl.store import Store


def populate(store: Store) -> dict[str, int]:
    """A small but complete history: versions on several keys, activations, a rollback, recipes, audit."""
    cam1 = store.save_calibration("camera", "cam0", None, {"K": [[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]],
                                                          "rms_px": 0.12}, {"views": [{"image": "a.png"}]}, "alice")
    cam2 = store.save_calibration("camera", "cam0", None, {"rms_px": 0.1}, {"views": []}, "bob", note="re-shot")
    he = store.save_calibration("handeye", "cam0", "ur0", {"T_tool_cam": [[1.0, 0, 0, 0.05]]},
                                {"robot_poses": [[0.1, 0.2, 0.3, 0.0, 3.14, 0.0]]}, "alice")
    store.activate(cam1.id, "eng")
    store.activate(cam2.id, "eng")
    store.rollback("camera", "cam0", None, "eng")
    store.activate(he.id, "eng")
    store.save_recipe(7, "bolt M8", {"model": "bolt.json", "min_score": 0.8}, "alice")
    store.save_recipe(7, "bolt M8", {"model": "bolt.json", "min_score": 0.85}, "bob")
    store.save_recipe(2, "washer", {"model": "washer.json"}, "alice")
    store.audit("eng", "robot.move", "ur0", {"x_mm": 100.0, "y_mm": -20.0}, "ok")
    return {"cam1": cam1.id, "cam2": cam2.id, "he": he.id}


def snapshot(store: Store) -> dict[str, Any]:
    """Everything the store answers about its cell (records complete, with inputs)."""
    keys = {(s.kind, s.camera_id, s.robot_id) for s in store.list_calibrations()}
    recipes = store.list_recipes()
    return {
        "summaries": store.list_calibrations(),
        "records": [store.get_calibration(s.id) for s in store.list_calibrations()],
        "active": {k: store.active(*k) for k in sorted(keys, key=str)},
        "history": {k: store.activation_history(*k) for k in sorted(keys, key=str)},
        "recipes": recipes,
        "recipe_versions": [store.get_recipe(r.recipe_id, v) for r in recipes for v in range(1, r.version + 1)],
        "audit": store.audit_log(limit=10_000),
    }


def without_ids(snap: dict[str, Any]) -> dict[str, Any]:
    """``snap`` with calibration ids replaced by (kind, camera, robot, version) and audit ids dropped:
    what must survive a restore that renumbered the rows."""
    key = {r.id: (r.kind, r.camera_id, r.robot_id, r.version) for r in snap["records"]}

    def target(t: str) -> str:
        if t.startswith("calibration:") and int(t.split(":")[1]) in key:
            return f"calibration:{key[int(t.split(':')[1])]}"
        return t

    return {
        "summaries": [{**s.to_dict(), "id": key[s.id]} for s in snap["summaries"]],
        "records": [{**r.to_dict(), "id": key[r.id]} for r in snap["records"]],
        "active": {k: None if r is None else key[r.id] for k, r in snap["active"].items()},
        "history": {k: [{**h, "calibration_id": key.get(h["calibration_id"])} for h in v]
                    for k, v in snap["history"].items()},
        "recipes": snap["recipes"],
        "recipe_versions": snap["recipe_versions"],
        "audit": [{**e.to_dict(), "id": None, "target": target(e.target)} for e in snap["audit"]],
    }


def damage_table(db: Path, table: str, seed: int = 7) -> None:
    """Write random bytes over the first page of ``table`` in the SQLite file ``db`` (its WAL folded in
    first; nothing may have the file open): what a failing disk or a stray write does to a store."""
    conn = sqlite3.connect(db)
    try:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        (root,) = conn.execute("SELECT rootpage FROM sqlite_master WHERE type = 'table' AND name = ?",
                               (table,)).fetchone()
        (page_size,) = conn.execute("PRAGMA page_size").fetchone()
    finally:
        conn.close()
    with db.open("r+b") as f:
        f.seek((root - 1) * page_size)
        f.write(random.Random(seed).randbytes(page_size))
