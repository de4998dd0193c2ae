"""A grasp you can see, and one that cannot grip refused at save (issue 36 item 2): the production cell's
part taught from the bounding box of a copy lying turned (the taught x axis is not the part's) closes the
fingers on a width the grip check refuses, and a grasp moved off the part closes across no material;
both 422 ``invalid_grasp`` with the reason. The upright part's grasp is drawn where the part is, closing
on its 30 mm."""

from __future__ import annotations

import math
from typing import Any

import httpx
import numpy as np
import pytest

from tests.support.app import in_process_cell
from tests.support.production_cell import CLEAR_POSE_UR, production_config

SEED, COUNT = 3, 12


def _yaw_deg(part: dict[str, Any]) -> float:
    T = np.array(part["T_base_part"])
    return math.degrees(math.atan2(T[1, 0], T[0, 0]))


def _recipe(model: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"name": "bracket", "models": [model], "plane_z_mm": 6.0, "grasp_z_mm": 0.0, "approach_height_mm": 40.0,
            "capture_pose_ur": CLEAR_POSE_UR,
            "gripper": {"grip_width_mm": 30.0, "device": {"io_id": "gripper0", "kind": "robotiq_2f"}}, **extra}


def _teach(http: httpx.Client, part: dict[str, Any], margin: float) -> dict[str, Any]:
    u, v, w, h = part["roi_px"]
    r = http.post("/pick/teach", json={"roi": [u - margin, v - margin, w + 2 * margin, h + 2 * margin],
                                      "name": "bracket"})
    assert r.status_code == 200, r.text
    return dict(r.json())


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("grasp")
    with in_process_cell(tmp, production_config(tmp, count=COUNT, seed=SEED)) as a, a.http() as http:
        r = http.post("/robots/robot0/move", json={"pose_ur": dict(zip(("x_m", "y_m", "z_m", "rx_rad", "ry_rad",
                                                                       "rz_rad"), CLEAR_POSE_UR, strict=True)),
                                                   "speed_m_s": 0.5})
        assert r.status_code == 200, r.text
        yield http, http.get("/sim/truth").json()


def test_the_upright_part_s_grasp_is_drawn_on_it_and_saves(cell: Any) -> None:
    http, truth = cell
    part = truth["parts"][0]
    model = _teach(http, part, 12)
    shown = http.post("/pick/grasp", json={"recipe": _recipe(model)})
    assert shown.status_code == 200, shown.text
    body = shown.json()
    assert body["problem"] is None and body["unavailable"] is None, body
    g = body["grasps"][0]
    u, v, w, h = part["roi_px"]
    assert abs(g["centre_px"][0] - (u + w / 2)) < 3 and abs(g["centre_px"][1] - (v + h / 2)) < 3
    assert abs(g["material_mm"] - 30.0) < 1.5, g  # the part's 30 mm across y
    assert g["open_mm"] == 85.0  # no open_width_mm: the stroke
    (a0, b0), (a1, b1) = g["fingers_px"]
    assert math.hypot(a1 - a0, b1 - b0) * g["mm_per_px"] == pytest.approx(85.0, rel=1e-3)
    saved = http.post("/recipes", json={"recipe_id": 1, "recipe": _recipe(model)})
    assert saved.status_code == 201, saved.text


def test_a_part_taught_turned_from_its_box_is_refused_with_the_reason(cell: Any) -> None:
    http, truth = cell
    turned = max(truth["parts"][1:], key=lambda p: abs((_yaw_deg(p) + 90) % 180 - 90))
    off = abs((_yaw_deg(turned) + 90) % 180 - 90)
    assert off > 20, f"the scatter has no part turned far enough ({off:.1f} deg)"
    model = _teach(http, turned, 6)
    r = http.post("/recipes", json={"recipe_id": 2, "recipe": _recipe(model)})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_grasp", err
    assert "grip_width_mm is 30 mm" in err["message"] and "taught turned" in err["message"], err["message"]
    shown = http.post("/pick/grasp", json={"recipe": _recipe(model)}).json()
    assert shown["problem"] == err["message"]
    assert shown["grasps"][0]["material_mm"] > 33.0  # the chord of the turned part, not its 30 mm
    assert http.get("/recipes/2").status_code == 404  # nothing stored


def test_a_grasp_off_the_part_closes_across_no_material(cell: Any) -> None:
    http, truth = cell
    model = _teach(http, truth["parts"][0], 12)
    r = http.post("/recipes", json={"recipe_id": 3, "recipe": _recipe(model, grasp_offset_mm=[45.0, 0.0])})
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert r.json()["error"]["code"] == "invalid_grasp" and "closes across no part material" in msg, msg
    # wider than the stroke: the fingers along the part's 50 mm bar (y = -9 mm) with a 40 mm stroke
    wide = _recipe(model, grasp_yaw_deg=90.0, grasp_offset_mm=[0.0, -9.0])
    wide["gripper"] = {"device": {"io_id": "gripper0", "kind": "robotiq_2f", "stroke_mm": 40.0}}
    r = http.post("/recipes", json={"recipe_id": 3, "recipe": wide})
    assert r.status_code == 422 and "wider than the gripper's stroke (40 mm)" in r.json()["error"]["message"], r.text
    # across the L's short leg (y = 0 runs through the notch): 30 mm of part from 25 mm on one side, beyond a
    # 40 mm opening centred on the reference point: a finger would come down on the part
    leg = _recipe(model, grasp_yaw_deg=90.0)
    leg["gripper"] = {"open_width_mm": 40.0, "device": {"io_id": "gripper0", "kind": "robotiq_2f"}}
    r = http.post("/recipes", json={"recipe_id": 3, "recipe": leg})
    assert r.status_code == 422 and "a finger would come down on the part" in r.json()["error"]["message"], r.text
    # without a parallel gripper device (a vacuum cup, or none named) there is no closing line to check
    cup = _recipe(model, grasp_offset_mm=[45.0, 0.0])
    cup["gripper"] = {"settle_s": 0.1}
    r = http.post("/recipes", json={"recipe_id": 3, "recipe": cup})
    assert r.status_code == 201, r.text


def test_the_drawing_of_a_recipe_it_cannot_read_says_why(cell: Any) -> None:
    http, truth = cell
    model = _teach(http, truth["parts"][0], 12)
    newer = {**model, "format_version": 99}
    r = http.post("/pick/grasp", json={"recipe": _recipe(newer)})
    assert r.status_code == 422 and r.json()["error"]["code"] in ("invalid_request", "invalid_model"), r.text
    assert "newer than this cellctl reads" in r.json()["error"]["message"]
