"""Stopping, pausing and resuming a served production run; the slot counter across a restart (scale 1)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from tests.support.production_cell import production_config, slot_error, teach_recipe, wait_ended, wait_for
from tests.support.served import start_served, stop_served


def truth_parts(http: Any) -> list[dict[str, Any]]:
    parts: list[dict[str, Any]] = http.get("/sim/truth").json()["parts"]
    return parts


def test_a_stop_with_a_part_held_latches_keeps_it_gripped_and_ends_the_run_stopped(tmp_path: Path) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=4, time_scale=0.5))
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http)
        run_id = http.post("/production/start", json={"recipe_id": 1}).json()["run_id"]
        deadline = time.monotonic() + 60
        while not any(p["state"] == "held" for p in truth_parts(http)):
            assert time.monotonic() < deadline, "no part was ever held"
            time.sleep(0.02)
        assert http.post("/robots/robot0/stop").status_code == 200
        end = wait_ended(http)
        assert end["state"] == "stopped" and end["ended_because"] == "stopped", end
        placed = end["counters"]["placed"]
        time.sleep(1.0)  # nothing more happens
        parts = truth_parts(http)
        assert [p["state"] for p in parts].count("held") == 1
        assert [p["state"] for p in parts].count("placed") == placed
        truth = http.get("/sim/truth").json()
        assert truth["gripper"]["closed"] is True
        assert http.get("/robots/robot0/motion").json()["latched"] is True
        assert http.get(f"/production/runs/{run_id}/cycles").json()[-1]["result"] == "stopped"
        # Resume the robot: the gripper stays closed, the part held; a new run is refused while it holds.
        assert http.post("/robots/robot0/resume").status_code == 200
        assert http.get("/sim/truth").json()["gripper"]["holding"] is not None
        again = http.post("/production/start", json={"recipe_id": 1})
        assert again.status_code == 409 and again.json()["error"]["code"] == "gripper_holding", again.text
    finally:
        stop_served(served)


def test_pause_waits_after_the_cycle_and_resume_goes_on(tmp_path: Path) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=3))
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http)
        http.post("/production/start", json={"recipe_id": 1})
        assert http.post("/production/pause").json()["state"] in ("pausing", "paused")
        paused = wait_for(http, lambda st: st["state"] == "paused")
        time.sleep(1.0)
        still = http.get("/production").json()
        assert still["state"] == "paused" and still["counters"]["placed"] == paused["counters"]["placed"] < 3
        pose = {"x_m": 0.45, "y_m": -0.3, "z_m": 0.3, "rx_rad": 3.14159, "ry_rad": 0.0, "rz_rad": 0.0}
        busy = http.post("/robots/robot0/move", json={"pose_ur": pose})
        assert busy.status_code == 409 and busy.json()["error"]["code"] == "robot_busy"  # the run owns the robot
        assert http.post("/production/resume").json()["state"] == "running"
        end = wait_ended(http)
        assert end["ended_because"] == "area_empty" and end["counters"]["placed"] == 3, end
    finally:
        stop_served(served)


def test_at_real_time_the_slot_counter_survives_a_restart(tmp_path: Path) -> None:
    config = production_config(tmp_path, count=3, time_scale=1.0)
    served = start_served(tmp_path, config)
    try:
        http = served.client(timeout_s=60)
        recipe = teach_recipe(http)
        r = http.post("/production/start", json={"recipe_id": 1, "count": 2})
        assert r.status_code == 202, r.text
        again = http.post("/production/start", json={"recipe_id": 1, "count": 2})
        assert again.status_code == 409 and again.json()["error"]["code"] in ("production_running", "robot_busy")
        end = wait_ended(http, timeout_s=120)
        assert end["ended_because"] == "count_reached" and end["counters"]["placed"] == 2 and end["next_slot"] == 2
        ms = end["cycle_ms"]
        # The second cycle's picture was taken while the first part was placed: the cycle hardly waited for it.
        assert ms["vision_median"] < 0.5 * ms["median"], ms
        from cellctl.production.config import GridPlace

        grid = GridPlace.model_validate(recipe["place"])
        placed = [p for p in truth_parts(http) if p["state"] == "placed"]
        assert len(placed) == 2
        for p in placed:
            err = min(slot_error(p["T_base_part"], grid.T_slot(k)) for k in range(2))
            assert err[0] < 1.0 and err[1] < 1.0, err
    finally:
        stop_served(served)
    served = start_served(tmp_path, config)
    try:
        http = served.client(timeout_s=60)
        st = http.get("/production").json()
        assert st["next_slot"] == 2 and st["ended_because"] == "count_reached", st
        put = http.put("/production/slot", json={"recipe_id": 1, "next_slot": 0})
        assert put.status_code == 200 and put.json()["next_slot"] == 0
        bad = http.put("/production/slot", json={"recipe_id": 1, "next_slot": 99})
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "invalid_slot"
        assert http.get("/production").json()["next_slot"] == 0
    finally:
        stop_served(served)
