"""The cell knows what it sees (issue 34, item 8), on the virtual production cell.

The red-team's scenario: right after the hand-eye capture the arm holds the calibration plate over
the pick area (the scene's home pose). A teach whose ROI the arm covers is refused with the reason
(409 ``arm_in_view``), and accepted once the arm is out of view; a pick picture taken with the arm
in view drops the matches on the arm. A run on parts its model does not match ends
``not_recognized`` (the picture shows objects), never ``area_empty``; the PLC code is 7.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from cellctl.pick.model import teach
from cellctl.plc.production import ENDED, RESULTS
from tests.support.app import AppCell, in_process_cell
from tests.support.production_cell import CLEAR_POSE_UR, production_config, teach_recipe, wait_ended

HOME_UR = [0.45, 0.0, 0.20, 3.14159265, 0.0, 0.0]


def pose(ur: list[float]) -> dict[str, float]:
    return dict(zip(("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"), ur, strict=True))


@pytest.fixture()
def cell(tmp_path: Path) -> Iterator[AppCell]:
    with in_process_cell(tmp_path, production_config(tmp_path, count=4)) as app:
        yield app


@pytest.mark.slow  # an in-process production cell, real-time motion at 0.2 x: ~20 s
def test_a_teach_with_the_arm_in_view_is_refused_then_accepted_clear_of_it(cell: AppCell) -> None:
    http = cell.http()
    assert http.post("/robots/robot0/move", json={"pose_ur": pose(HOME_UR), "speed_m_s": 0.5}).status_code == 200
    truth = http.get("/sim/truth").json()
    # The parts whose box the arm (the plate over the area) covers: a teach there learns the plate's edge.
    for part in truth["parts"]:
        if part["roi_px"] is None:
            continue
        u, v, w, h = part["roi_px"]
        r = http.post("/pick/teach", json={"roi": [u - 12, v - 12, w + 24, h + 24], "name": "bracket"})
        if r.status_code == 409:
            err = r.json()["error"]
            assert err["code"] == "arm_in_view" and "calibration plate" in err["message"], err
            assert "move the robot out of the camera's view" in err["message"]
            break
        assert r.status_code == 200, r.text
    else:
        pytest.fail("no part's ROI was refused with the plate over the pick area")
    assert http.post("/robots/robot0/move", json={"pose_ur": pose(CLEAR_POSE_UR), "speed_m_s": 0.5}).status_code == 200
    taught = http.post("/pick/teach", json={"roi": [u - 12, v - 12, w + 24, h + 24], "name": "bracket"})
    assert taught.status_code == 200, taught.text


@pytest.mark.slow
def test_a_pick_picture_with_the_arm_in_view_drops_the_matches_on_the_arm(cell: AppCell) -> None:
    http = cell.http()
    recipe = teach_recipe(http)  # taught clear of the view
    # A fixed camera's recipe need not name a capture pose: the picture is taken wherever the arm is.
    saved = http.post("/recipes", json={"recipe_id": 3, "recipe": {**recipe, "capture_pose_ur": None}})
    assert saved.status_code == 201, saved.text
    assert http.post("/robots/robot0/move", json={"pose_ur": pose(HOME_UR), "speed_m_s": 0.5}).status_code == 200
    clear = http.post("/pick", json={"recipe_id": 3})
    assert clear.status_code == 200, clear.text
    answer = clear.json()
    assert answer["arm_in_view"] == "the tool and the calibration plate it carries"
    truth = http.get("/sim/truth").json()
    T_cam_base = np.linalg.inv(np.array(truth["T_base_cam"]))
    tool = np.array(truth["T_base_tool"])[:3, 3]
    tool_px = T_cam_base[:3, :3] @ tool + T_cam_base[:3, 3]
    assert tool_px[2] > 0
    # No pick lies where the plate is: every pick maps to a part, none to the plate around the tool.
    for p in answer["picks"]:
        xy = np.array([p["pick_pose"]["x_mm"], p["pick_pose"]["y_mm"]])
        assert np.linalg.norm(xy - tool[:2] * 1e3) > 40.0, (p["pick_pose"], tool)


def other_part_model(size: tuple[int, int]) -> dict:  # type: ignore[type-arg]
    """A part model of a shape the cell does not hold (a ring), taught on an image of the camera's size."""
    w, h = size
    img = np.full((h, w), 90, np.uint8)
    cv2.circle(img, (w // 2, h // 2), 45, 230, -1)
    cv2.circle(img, (w // 2, h // 2), 20, 90, -1)
    model: dict = teach(img, (w / 2 - 70, h / 2 - 70, 140, 140), mode="shape", name="ring").to_dict()  # type: ignore[type-arg]
    return model


@pytest.mark.slow
def test_a_run_on_parts_its_model_does_not_match_ends_not_recognized(cell: AppCell) -> None:
    http = cell.http()
    recipe = teach_recipe(http)
    recipe["models"] = [other_part_model(tuple(recipe["models"][0]["teach"]["image_size"]))]
    recipe["name"] = "ring"
    assert http.post("/recipes", json={"recipe_id": 2, "recipe": recipe}).status_code == 201
    r = http.post("/production/start", json={"recipe_id": 2, "count": 0})
    assert r.status_code == 202, r.text
    end = wait_ended(http)
    assert end["state"] == "complete" and end["ended_because"] == "not_recognized", end
    assert end["counters"]["placed"] == 0 and end["counters"]["empty_area"] == 0, end
    cycles = http.get(f"/production/runs/{r.json()['run_id']}/cycles").json()
    assert [c["result"] for c in cycles] == ["not_recognized"], cycles
    assert "object(s) in the search region" in cycles[0]["detail"]
    assert ENDED["not_recognized"] == 7 and RESULTS["not_recognized"] == 9
    assert all(p["state"] == "in_area" for p in http.get("/sim/truth").json()["parts"])
