"""Production runs on a served production cell (the robot moves in real time, scaled), against truth."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.production.cell import production_config, serve, slot_error, teach_recipe, wait_ended
from tests.support.served import Served, stop_served


@pytest.fixture()
def served4(tmp_path: Path) -> Iterator[Served]:
    served = serve(tmp_path, production_config(tmp_path, count=4))
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
    from cellctl.pick.place import GridPlace

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
