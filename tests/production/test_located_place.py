"""A place located by vision: a nest plate (the fixture) found in the same picture as the parts.

The fixture is taught from a live frame and the place's slots are set in its frame on one cell;
on a second cell the plate lies elsewhere, turned the other way: a run places every part into
its pockets within 1 mm / 1 deg of the truth, and the parts lying in the pockets are not picked
again (the run ends area_empty)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI

from calibration import geometry as g
from cellctl.mapping import active_mapping
from cellctl.pick.fixture import locate_fixture
from cellctl.production.config import LocatedPlace
from tests.support.app import AppCell, in_process_cell
from tests.support.production_cell import production_config, slot_error, teach_recipe, wait_ended

PICK_AREA = {"x_mm": [330.0, 605.0], "y_mm": [-90.0, 125.0]}
"""The scatter kept clear of the plate below the area, still in the camera's view."""
PLATE: dict[str, Any] = {
    "outline_mm": [[-65, -24], [65, -24], [65, 10], [51, 24], [-65, 24]],  # a cut corner: one way round
    "holes_mm": [[[-62, -18], [-6, -18], [-6, 18], [-62, 18]], [[6, -18], [62, -18], [62, 18], [6, 18]]],
    "slots_mm": [[-34, 0], [34, 0]],
}
TAUGHT_AT = {"x_mm": 430.0, "y_mm": -150.0, "angle_deg": 2.0}
MOVED_TO = {"x_mm": 445.0, "y_mm": -149.0, "angle_deg": -3.0}


def scene(at: dict[str, float]) -> dict[str, Any]:
    return {"pick_area": PICK_AREA, "fixture": {**PLATE, **at}}


def services_of(cell: AppCell) -> Any:
    app = cell.client.app
    assert isinstance(app, FastAPI)
    return app.state.services


def teach_located_place(cell: AppCell) -> dict[str, Any]:
    """Teach the plate from a live frame, find it as a run would, and set its two pockets as slots
    in its frame (from the truth of where they are): the recipe's located place section."""
    http = cell.http()
    truth = http.get("/sim/truth").json()
    u, v, w, h = truth["fixture"]["roi_px"]
    model = http.post("/pick/teach", json={"roi": [u - 10, v - 10, w + 20, h + 20], "name": "plate"})
    assert model.status_code == 200, model.text
    place = LocatedPlace.model_validate({"kind": "located", "model": model.json(), "plane_z_mm": 1.0,
                                         "origin_ur": [0.0] * 6, "cols": 2, "min_score": 0.6})
    services = services_of(cell)
    pixels = services.cell.camera("cam0").ensure_open().grab(timeout_s=5.0).pixels
    robot = services.cell.robot("robot0").ensure_open()
    mapping = active_mapping(services, "cam0", "robot0", "auto", True)
    T_fix, found = locate_fixture(place, pixels, mapping, robot.state().T_base_tool)
    assert T_fix is not None and found["score"] > 0.9, found
    slots = [np.array(T) for T in truth["fixture"]["slots"]]
    T_origin = g.invert(T_fix) @ slots[0]
    pitch = (g.invert(slots[0]) @ slots[1])[:3, 3] * 1e3  # the second pocket in the first's frame
    assert abs(pitch[1]) < 0.5 and abs(pitch[2]) < 0.5, pitch
    section: dict[str, Any] = place.model_dump(mode="json")
    section.update(origin_ur=[float(x) for x in g.transform_to_ur_pose(T_origin)], pitch_mm=[float(pitch[0]), 0.0])
    return section


@pytest.mark.slow  # two in-process production cells, two parts placed at 0.2 x real time: ~30 s
def test_a_located_place_follows_the_fixture_where_it_lies(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    with in_process_cell(a, production_config(a, count=2, scene=scene(TAUGHT_AT))) as cell:
        http = cell.http()
        recipe = teach_recipe(http)
        recipe["place"] = teach_located_place(cell)
        # A fixture not found (here: a score no match reaches) fails the run before any pick, saying so.
        unseen = {**recipe, "place": {**recipe["place"], "min_score": 1.0}}
        assert http.post("/recipes", json={"recipe_id": 2, "recipe": unseen}).status_code == 201
        assert http.post("/production/start", json={"recipe_id": 2}).status_code == 202
        end = wait_ended(http)
        assert end["state"] == "failed" and "fixture was not found" in end["error"], end
        assert end["counters"]["picked"] == 0 and {p["state"] for p in http.get("/sim/truth").json()["parts"]} == {
            "in_area"}
        last = http.get(f"/production/runs/{end['run_id']}/cycles").json()[-1]
        assert last["result"] == "vision_failed" and last["frame_kept"] is True, last
    with in_process_cell(b, production_config(b, count=2, scene=scene(MOVED_TO))) as cell:
        http = cell.http()
        assert http.post("/recipes", json={"recipe_id": 1, "recipe": recipe}).status_code == 201
        start = http.post("/production/start", json={"recipe_id": 1})
        assert start.status_code == 202, start.text
        end = wait_ended(http)
        assert end["ended_because"] == "area_empty" and end["counters"]["placed"] == 2, end
        truth = http.get("/sim/truth").json()
        slots = [np.array(T) for T in truth["fixture"]["slots"]]
        errors = {}
        for p in truth["parts"]:
            assert p["state"] == "placed", p
            k = min(range(len(slots)), key=lambda j: slot_error(p["T_base_part"], slots[j])[0])
            errors[k] = slot_error(p["T_base_part"], slots[k])
        assert sorted(errors) == [0, 1], errors  # one part in each pocket
        assert all(mm < 1.0 and deg < 1.0 for mm, deg in errors.values()), errors
        run_id = start.json()["run_id"]
        cycles = http.get(f"/production/runs/{run_id}/cycles").json()
        assert [c["result"] for c in cycles] == ["placed", "placed", "empty"], cycles
        assert all(c["fixture"]["score"] > 0.6 for c in cycles), [c["fixture"] for c in cycles]
        # The plate moved 15 mm and turned 5 deg: the places were not where it was taught.
        moved = math.hypot(MOVED_TO["x_mm"] - TAUGHT_AT["x_mm"], MOVED_TO["y_mm"] - TAUGHT_AT["y_mm"])
        assert moved > 10
