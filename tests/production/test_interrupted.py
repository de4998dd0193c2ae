"""A run the service did not end (the store says it still runs, a slot claimed: what a kill -9 leaves)
is ended ``interrupted`` at the next start: where it was, the held part's record, the slot in doubt,
the robot latched; REST and the PLC's production block show it; a new run is accepted, skips the
slot and ``GET /production`` keeps naming it. (The real kill -9: tests/production/test_exactly_once.py.)"""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi import FastAPI

from cellctl.config import load_config
from cellctl.plc.production import ENDED, RESULTS, STATES, production_values
from cellctl.store import open_store
from tests.support.app import in_process_cell
from tests.support.production_cell import production_config, teach_recipe, wait_ended

PICK = {"x_mm": 400.0, "y_mm": 20.0, "z_mm": 6.0, "rx_rad": 3.14, "ry_rad": 0.0, "rz_rad": 0.0}


@pytest.mark.slow  # an in-process production cell and one placed part at 0.1 x real time: ~6 s
def test_an_unended_run_ends_interrupted_at_start_with_its_slot_in_doubt_and_the_robot_latched(
        tmp_path: Path) -> None:
    config = production_config(tmp_path, count=2, time_scale=0.1)
    with open_store(load_config(config)) as store:
        run_id = store.new_run(1, "robot0", "eng")
        store.claim_slot(1, 0, run_id, 3, {"pick_pose": PICK})
        store.set_progress(run_id, {"phase": "carrying", "n": 3, "slot": 0, "pick_pose": PICK, "holding": True})
        store.add_cycle(run_id, {"n": 1, "t": 1.0, "result": "grip_failed", "slot": None})
        store.add_cycle(run_id, {"n": 2, "t": 2.0, "result": "grip_failed", "slot": None})
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        st = http.get("/production").json()
        assert st["run_id"] == run_id and st["state"] == st["ended_because"] == "interrupted", st
        assert st["progress"]["phase"] == "carrying" and "did not end it" in st["stop_reason"], st
        assert [(d["slot"], d["run_id"]) for d in st["slots_in_doubt"]] == [(0, run_id)], st
        last = http.get(f"/production/runs/{run_id}/cycles").json()[-1]
        assert (last["n"], last["result"], last["phase"], last["held"], last["slot"], last["slot_state"]) == (
            3, "interrupted", "carrying", True, 0, "in_doubt"), last
        assert last["pick_pose"] == PICK
        motion = http.get("/robots/robot0/motion").json()
        assert motion["latched"] is True, motion
        app = cell.client.app
        assert isinstance(app, FastAPI)
        plc = production_values(app.state.services)
        assert (plc["run_id"], plc["state"], plc["ended"], plc["last_result"], plc["last_slot"]) == (
            run_id, STATES["interrupted"], ENDED["interrupted"], RESULTS["interrupted"], 0), plc
        assert plc["next_slot"] == 1  # past the slot in doubt
        assert http.post("/robots/robot0/resume").status_code == 200
        teach_recipe(http)
        r = http.post("/production/start", json={"recipe_id": 1, "count": 1})
        assert r.status_code == 202, r.text
        end = wait_ended(http)
        assert end["run_id"] == run_id + 1 and end["counters"]["placed"] == 1, end
        assert [d["slot"] for d in end["slots_in_doubt"]] == [0], end  # still named until confirmed
        placed = [c for c in http.get(f"/production/runs/{run_id + 1}/cycles").json() if c["result"] == "placed"]
        assert [c["slot"] for c in placed] == [1]  # slot 0 skipped
        bad = http.post("/production/slots/1/confirm", json={"recipe_id": 1, "occupied": True})
        assert bad.status_code == 404 and bad.json()["error"]["code"] == "slot_not_in_doubt", bad.text
        ok = http.post("/production/slots/0/confirm", json={"recipe_id": 1, "occupied": False})
        assert ok.status_code == 200 and ok.json()["next_slot"] == 2, ok.text  # 1 is used: 0 stays a gap
        assert http.get("/production").json()["slots_in_doubt"] == []
