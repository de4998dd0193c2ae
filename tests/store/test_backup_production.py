"""A production run, ``cellctl store backup``, ``cellctl store restore`` into a new store: the runs, the
cycle records with their failure-frame references, the slot counter and the slots in doubt come back
(SQLite in both backup formats, PostgreSQL as JSON)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from cellctl.cli import main
from cellctl.config import load_config
from cellctl.production.frames import FailureFrames
from cellctl.store import Store, open_store
from tests.support.app import in_process_cell
from tests.support.production_cell import production_config, teach_recipe, wait_ended


def _production(store: Store) -> dict[str, Any]:
    last = store.last_run()
    assert last is not None
    runs = [store.get_run(i) for i in range(1, int(last["run_id"]) + 1)]
    return {"runs": runs, "cycles": {r["run_id"]: store.cycles(r["run_id"]) for r in runs},
            "next_slot": store.next_slot(1), "free_slot": store.free_slot(1), "in_doubt": store.slots_in_doubt()}


def _with_store(config: Path, store: dict[str, str], path: Path) -> Path:
    cfg = yaml.safe_load(config.read_text())
    cfg["store"] = store
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.slow  # an in-process production cell (motion at 0.1 x real time), then backups and restores: ~6 s
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_production_run_survives_backup_and_restore_into_a_new_store(
        backend: str, tmp_path: Path, request: pytest.FixtureRequest, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))  # the service's, where its frames are kept
    config = production_config(tmp_path, count=2, time_scale=0.1)
    if backend == "postgresql":
        cluster = request.getfixturevalue("postgres")
        config = _with_store(config, {"url": cluster.create_database("line_a")}, tmp_path / "cell.yaml")
        from tests.support.production_cell import store_truth

        store_truth(config, tmp_path / "scene.yaml")
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        teach_recipe(http)
        run_id = http.post("/production/start", json={"recipe_id": 1}).json()["run_id"]
        end = wait_ended(http)
        assert end["ended_because"] == "area_empty" and end["counters"]["placed"] == 2, end
    frames = FailureFrames.for_config(load_config(config))
    with open_store(load_config(config)) as store:
        # A slot in doubt (as a Stop between claim and release leaves one) must come back too.
        store.claim_slot(1, 2, run_id, 99, {"pick_pose": None})
        store.slot_in_doubt(1, 2, run_id, {"phase": "over_slot"})
        before = _production(store)
    cycles = before["cycles"][run_id]
    assert [c["result"] for c in cycles] == ["placed", "placed", "empty"], cycles
    assert cycles[-1]["frame_kept"] is True and before["next_slot"] == 3 and before["free_slot"] == 3
    kept = frames.load(run_id, cycles[-1]["n"])  # the failure frame the record refers to

    targets: list[tuple[str, dict[str, str]]] = []
    if backend == "sqlite":
        targets = [("sqlite", {"path": str(tmp_path / "new-a.db")}), ("json", {"path": str(tmp_path / "new-b.db")})]
    else:
        cluster = request.getfixturevalue("postgres")
        targets = [("json", {"url": cluster.create_database("line_a_restored")})]
    for fmt, new_store in targets:
        out = tmp_path / f"backup-{fmt}.bin"
        capsys.readouterr()
        assert main(["store", "backup", "--config", str(config), "--out", str(out), "--format", fmt]) == 0
        counts = yaml.safe_load(capsys.readouterr().out)["counts"]
        assert counts["production_runs"] == 1 and counts["production_cycles"] == 3, counts
        assert counts["production_slots"] == 1 and counts["production_slot_claims"] == 1, counts
        new_config = _with_store(config, new_store, tmp_path / f"new-{fmt}.yaml")
        assert main(["store", "restore", "--config", str(new_config), "--from", str(out), "--who", "maint"]) == 0
        with open_store(load_config(new_config)) as restored:
            after = _production(restored)
        assert after == before, fmt
        record = after["cycles"][run_id][-1]
        assert record["frame_kept"] is True
        again = FailureFrames.for_config(load_config(new_config)).load(int(record["run_id"]), int(record["n"]))
        assert again.frame_id == kept.frame_id and (again.pixels == kept.pixels).all()
