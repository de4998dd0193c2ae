"""Production runs on a served production cell (the robot moves in real time, scaled), against truth."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.support.production_cell import production_config, slot_error, teach_recipe, wait_ended
from tests.support.served import Served, start_served, stop_served


@pytest.fixture()
def served4(tmp_path: Path) -> Iterator[Served]:
    served = start_served(tmp_path, production_config(tmp_path, count=4))
    try:
        yield served
    finally:
        stop_served(served)


def test_a_run_empties_the_area_into_the_grid(served4: Served) -> None:
    http = served4.client(timeout_s=60)
    recipe = teach_recipe(http)
    r = http.post("/production/start", json={"recipe_id": 1, "count": 0})
    assert r.status_code == 202, r.text
    run_id = r.json()["run_id"]
    end = wait_ended(http)
    assert end["state"] == "complete" and end["ended_because"] == "area_empty", end
    c = end["counters"]
    assert c["placed"] == 4 and c["picked"] == 4 and c["empty_area"] == 1, c
    assert end["next_slot"] == 4
    truth = http.get("/sim/truth").json()
    grid = recipe["place"]
    placed = sorted((p for p in truth["parts"] if p["state"] == "placed"), key=lambda p: p["T_base_part"][0][3])
    assert len(placed) == 4 and all(p["state"] == "placed" for p in truth["parts"])
    from cellctl.production.config import GridPlace

    slots = [GridPlace.model_validate(grid).T_slot(k) for k in range(4)]
    for p in truth["parts"]:
        err = min(slot_error(p["T_base_part"], T) for T in slots)
        assert err[0] < 1.0 and err[1] < 1.0, (p["id"], err)
    cycles = http.get(f"/production/runs/{run_id}/cycles").json()
    assert [c["result"] for c in cycles] == ["placed"] * 4 + ["empty"]
    assert [c["slot"] for c in cycles[:4]] == [0, 1, 2, 3]
    for c in cycles[:4]:
        assert c["score"] > 0.7 and c["durations_ms"]["motion"] > 0 and c["frame_id"] is not None
    csv_text = http.get(f"/production/runs/{run_id}/cycles", params={"format": "csv"}).text
    assert csv_text.splitlines()[0].startswith("n,t,result,slot") and len(csv_text.splitlines()) == 6
    ms = end["cycle_ms"]
    assert ms["median"] > 0 and ms["motion_median"] > 0 and ms["p95"] >= ms["median"]
    assert np.isfinite([ms["vision_median"], ms["gripper_median"]]).all()


def test_grip_failures_are_retried_and_counted(tmp_path: Path) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=3, scene={"gripper": {"fail_probability": 0.5}}))
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http, gripper={"grip_width_mm": 30.0, "settle_s": 0.05,
                                    "device": {"io_id": "gripper0", "kind": "robotiq_2f", "retries": 8}})
        run_id = http.post("/production/start", json={"recipe_id": 1}).json()["run_id"]
        end = wait_ended(http)
        c = end["counters"]
        assert end["ended_because"] == "area_empty" and c["placed"] == 3, end
        assert c["grip_failures"] >= 1 and c["retries"] == c["grip_failures"] and c["skipped"] == 0, c
        results = [r["result"] for r in http.get(f"/production/runs/{run_id}/cycles").json()]
        assert results.count("grip_failed") == c["grip_failures"] and results.count("placed") == 3
        assert all(p["state"] == "placed" for p in http.get("/sim/truth").json()["parts"])
    finally:
        stop_served(served)


def test_only_unreachable_parts_end_none_pickable_not_area_empty(tmp_path: Path) -> None:
    unreachable = [{"x_mm": 640.0, "y_mm": 40.0, "angle_deg": 30.0},
                   {"x_mm": 640.0, "y_mm": -50.0, "angle_deg": -100.0}]  # beyond the envelope's x = 615 mm
    served = start_served(tmp_path, production_config(tmp_path, count=1, scene={"unreachable": unreachable}))
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http)
        first = http.post("/production/start", json={"recipe_id": 1}).json()["run_id"]
        end = wait_ended(http)  # the taught part is placed, then only the unreachable ones are left
        assert end["ended_because"] == "none_pickable" and end["state"] == "complete", end
        c = end["counters"]
        assert c["placed"] == 1 and c["unreachable"] == 2 and c["empty_area"] == 0, c
        assert end["totals"]["placed"] == 1
        last = http.get(f"/production/runs/{first}/cycles").json()[-1]
        assert last["result"] == "none_pickable", last
        assert "2 not pickable" in last["detail"] and "envelope" in last["detail"], last
        states = [p["state"] for p in http.get("/sim/truth").json()["parts"]]
        assert states == ["placed", "in_area", "in_area"]
    finally:
        stop_served(served)


def test_a_full_place_grid_fails_the_run_saying_so_and_the_slot_can_be_reset(tmp_path: Path) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=2))
    try:
        http = served.client(timeout_s=60)
        grid = {"kind": "grid", "origin_ur": [0.33, -0.23, 0.006, 0.0, 0.0, 0.0], "rows": 1, "cols": 1,
                "pitch_mm": [55.0, -45.0]}
        teach_recipe(http, place=grid)
        http.post("/production/start", json={"recipe_id": 1})
        end = wait_ended(http)
        assert end["state"] == "failed" and end["ended_because"] == "failed", end
        assert end["counters"]["placed"] == 1 and "full" in end["error"], end
        parts = http.get("/sim/truth").json()["parts"]
        assert sorted(p["state"] for p in parts) == ["in_area", "placed"]  # checked before the pick
        reset = http.put("/production/slot", json={"recipe_id": 1, "next_slot": 0})
        assert reset.status_code == 200 and reset.json()["next_slot"] == 0
        assert http.get("/production").json()["next_slot"] == 0
        opened = http.post("/production/gripper/open", params={"recipe_id": 1})
        assert opened.status_code == 200 and opened.json()["holding"] is False
    finally:
        stop_served(served)
