"""Hostile numbers at the edge of a served cell: every one answers a 4xx naming the field, never 200/500.

The cell is the virtual cell with its true calibrations active and recipe 1 (the bracket) stored
(``tests.plc.conftest.prepare_cell``): the real app with its lifespan, in this process behind
FastAPI's TestClient (``tests.support.app``); nothing here depends on uvicorn or a socket (the
served floods and slow bodies: test_floods.py, test_edge.py). The list is issue 12's:
NaN/Infinity/1e308 in recipes, ``min_score 1e-9``, absurd and millimetre robot poses for ``/map``,
moves at 1e301 m or 1e-300 m/s, JSON's NaN/Infinity literals (Python's ``json`` accepts them) on
any route and under any content type.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.plc.conftest import RECIPE, prepare_cell
from tests.support.app import AppCell, in_process_cell

DOWN = {"rx_rad": 3.14159, "ry_rad": 0.0, "rz_rad": 0.0}


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, dict[str, Any]]]:
    tmp = tmp_path_factory.mktemp("hostile")
    path, _ = prepare_cell(tmp, {})
    with in_process_cell(tmp, config=path) as app, app.http() as http:
        recipe = http.get(f"/recipes/{RECIPE}").json()["data"]
        yield app, recipe


def strict_json(text: str) -> Any:
    """Parse a response body, failing on NaN/Infinity (which a standard JSON parser would refuse)."""
    def refuse(literal: str) -> None:
        raise AssertionError(f"response holds {literal}: {text[:200]}")
    return json.loads(text, parse_constant=refuse)


def refused(r: httpx.Response, field: str, status: int = 422) -> str:
    assert r.status_code == status, (r.status_code, r.text[:300])
    message: str = strict_json(r.text)["error"]["message"]
    assert field in message, (field, message)
    return message


def raw_post(http: httpx.Client, path: str, text: str, content_type: str = "application/json") -> httpx.Response:
    return http.post(path, content=text.encode(), headers={"Content-Type": content_type})


# -- JSON's non-finite literals, on any route and any content type --------------------------------------

@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999", "-2.5E+400"])
def test_non_finite_literals_are_refused_naming_the_field(cell: tuple[AppCell, dict[str, Any]], literal: str) -> None:
    served, _ = cell
    with served.http() as http:
        for path, text, field in (
            ("/map", f'{{"u_px": {literal}, "v_px": 10}}', "body.u_px"),
            ("/map", f'{{"u_px": 10, "v_px": 10, "plane_z_mm": {literal}}}', "body.plane_z_mm"),
            ("/map", f'{{"u_px": 1, "v_px": 2, "robot_pose_ur": [0.4, 0, 0.5, {literal}, 0, 0]}}',
             "body.robot_pose_ur.3"),
            ("/robots/robot0/move", f'{{"pose_ur": {{"x_m": 0.4, "y_m": 0, "z_m": {literal}, "rx_rad": 3.14, '
                                    '"ry_rad": 0, "rz_rad": 0}}', "body.pose_ur.z_m"),
            ("/pick/teach", f'{{"roi": [10, 10, {literal}, 10]}}', "body.roi.2"),
            ("/routines/verify", f'{{"tolerance_px": {literal}}}', "body.tolerance_px"),
            ("/pick", f'{{"recipe_id": 1, "extra": [{{"deep": {literal}}}]}}', "body.extra.0.deep"),
        ):
            for content_type in ("application/json", "text/plain"):
                msg = refused(raw_post(http, path, text, content_type), field)
                assert literal in msg and "finite" in msg


def test_a_body_is_not_parsed_before_the_token_is_checked(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, _ = cell
    r = served.client.post("/map", content=b'{"u_px": NaN, "v_px": 1}',
                           headers={"Content-Type": "application/json"})
    assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized", r.text


def test_words_that_contain_nan_are_not_numbers(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, recipe = cell
    body = {"recipe_id": 41, "recipe": {**recipe, "name": "NaNo Infinity bracket 1e999"}}
    with served.http() as http:
        r = http.post("/recipes", json=body)
        assert r.status_code == 201, r.text
        assert http.get("/recipes/41").json()["data"]["name"] == "NaNo Infinity bracket 1e999"


# -- recipes --------------------------------------------------------------------------------------------

RECIPE_CASES: list[tuple[str, Any, str]] = [
    ("plane_z_mm", 1e308, "body.recipe.plane_z_mm"),
    ("plane_z_mm", -1e6, "body.recipe.plane_z_mm"),
    ("grasp_z_mm", 1e308, "body.recipe.grasp_z_mm"),
    ("grasp_offset_mm", [0.0, 1e308], "body.recipe.grasp_offset_mm.1"),
    ("approach_height_mm", 1e308, "body.recipe.approach_height_mm"),
    ("approach_height_mm", -5.0, "body.recipe.approach_height_mm"),
    ("grasp_yaw_deg", 1e308, "body.recipe.grasp_yaw_deg"),
    ("grasp_yaw_deg", "nan", "body.recipe.grasp_yaw_deg"),
    ("tool_rotvec_rad", [1e308, 0.0, 0.0], "body.recipe.tool_rotvec_rad.0"),
    ("speed_m_s", 1e-300, "body.recipe.speed_m_s"),
    ("speed_m_s", 1e308, "body.recipe.speed_m_s"),
    ("plane_z_mm", "Infinity", "body.recipe.plane_z_mm"),
    ("plane_z_mm", 10**400, "body.recipe.plane_z_mm"),
    ("search.min_score", 1e-9, "body.recipe.search.min_score"),
    ("search.min_score", 0.0, "body.recipe.search.min_score"),
    ("search.max_count", 0, "body.recipe.search.max_count"),
    ("search.angle_extent_deg", 0.0, "body.recipe.search.angle_extent_deg"),
    ("search.angle_start_deg", 1e308, "body.recipe.search.angle_start_deg"),
    ("search.roi", [0.0, 0.0, 1e308, 10.0], "body.recipe.search.roi.2"),
    ("search.timeout_s", 1e308, "body.recipe.search.timeout_s"),
]


@pytest.mark.parametrize(("key", "value", "field"), RECIPE_CASES, ids=[f"{k}={v!s:.12}" for k, v, _ in RECIPE_CASES])
def test_recipe_numbers_out_of_range_are_refused(cell: tuple[AppCell, dict[str, Any]], key: str, value: Any,
                                                 field: str) -> None:
    served, recipe = cell
    r = copy.deepcopy(recipe)
    if key.startswith("search."):
        r.setdefault("search", {})[key.removeprefix("search.")] = value
    else:
        r[key] = value
    with served.http() as http:
        msg = refused(http.post("/recipes", json={"recipe_id": 40, "recipe": r}), field)
        if key == "search.min_score":
            assert "0.05" in msg
        assert http.get("/recipes/40").status_code == 404  # nothing was stored


def test_a_sane_recipe_still_saves_and_picks(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, recipe = cell
    with served.http() as http:
        assert http.post("/recipes", json={"recipe_id": 42, "recipe": recipe}).status_code == 201
        r = http.post("/pick", json={"recipe_id": 42})
        assert r.status_code == 200, r.text
        answer = strict_json(r.text)
        assert answer["picks"] and all(p["reachable"] for p in answer["picks"][:1])


# -- /map -----------------------------------------------------------------------------------------------

MAP_CASES: list[tuple[dict[str, Any], str]] = [
    ({"robot_pose_ur": [1e301, 0.0, 0.5, 3.14159, 0.0, 0.0]}, "robot_pose_ur"),
    ({"robot_pose_ur": [0.4, 0.0, 0.5, 1e301, 0.0, 0.0]}, "robot_pose_ur"),
    ({"robot_pose_ur": [400.0, 0.0, 500.0, 3.14159, 0.0, 0.0]}, "robot_pose_ur"),  # millimetres, not metres
    ({"robot_pose_ur": [40.0, 0.0, 50.0, 3.14159, 0.0, 0.0]}, "look like millimetres"),
    ({"robot_pose_ur": [0.4, 0.0, 0.5]}, "robot_pose_ur"),
    ({"u_px": 1e6}, "u_px"),
    ({"v_px": -1e5}, "v_px"),
    ({"plane_z_mm": 1e308}, "plane_z_mm"),
    ({"plane_z_mm": 1e5}, "plane"),
]


@pytest.mark.parametrize(("change", "field"), MAP_CASES, ids=[str(c) for c, _ in MAP_CASES])
def test_map_refuses_absurd_inputs(cell: tuple[AppCell, dict[str, Any]], change: dict[str, Any], field: str) -> None:
    served, _ = cell
    body = {"u_px": 640.0, "v_px": 480.0, "plane_z_mm": 0.0, **change}
    with served.http() as http:
        r = http.post("/map", json=body)
        assert r.status_code == 422, r.text
        assert field in strict_json(r.text)["error"]["message"]


def test_map_answers_finite_numbers_for_sane_inputs(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, _ = cell
    with served.http() as http:
        for pose in (None, [0.4, 0.0, 0.5, 3.14159, 0.0, 0.0]):
            r = http.post("/map", json={"u_px": 640.0, "v_px": 480.0, "plane_z_mm": 0.0, "robot_pose_ur": pose})
            assert r.status_code == 200, r.text
            out = strict_json(r.text)
            assert all(isinstance(out[k], float) and abs(out[k]) < 1e4 for k in ("x_mm", "y_mm", "z_mm"))
            assert all(0 <= s < 10 for s in out["sigma_mm"])


# -- moves ----------------------------------------------------------------------------------------------

MOVE_CASES: list[tuple[dict[str, Any], str]] = [
    ({"pose_ur": {"x_m": 1e301, "y_m": 0.0, "z_m": 0.3, **DOWN}}, "pose_ur"),
    ({"pose_ur": {"x_m": 400.0, "y_m": 0.0, "z_m": 300.0, **DOWN}}, "pose_ur"),
    ({"pose_ur": {"x_m": 0.4, "y_m": 0.0, "z_m": 0.3, "rx_rad": 1e301, "ry_rad": 0.0, "rz_rad": 0.0}}, "pose_ur"),
    ({"T_base_tool": [[1, 0, 0, 1e301], [0, -1, 0, 0], [0, 0, -1, 0.3], [0, 0, 0, 1]]}, "T_base_tool"),
    ({"T_base_tool": [[1e300, 0, 0, 0.4], [0, -1, 0, 0], [0, 0, -1, 0.3], [0, 0, 0, 1]]}, "T_base_tool"),
    ({"T_base_tool": [[1, 0, 0, 0.4], [0, -1, 0, 0], [0, 0, -1, 0.3], [5, 0, 0, 1]]}, "T_base_tool"),
    ({"pose_ur": {"x_m": 0.4, "y_m": 0.0, "z_m": 0.3, **DOWN}, "speed_m_s": 1e-300}, "m/s"),
    ({"pose_ur": {"x_m": 0.4, "y_m": 0.0, "z_m": 0.3, **DOWN}, "speed_m_s": 1e-6}, "m/s"),
    ({"pose_ur": {"x_m": 0.4, "y_m": 0.0, "z_m": 0.3, **DOWN}, "speed_m_s": 1e308}, "speed_m_s"),
]


@pytest.mark.parametrize(("body", "field"), MOVE_CASES, ids=[str(b)[:60] for b, _ in MOVE_CASES])
def test_moves_with_absurd_numbers_are_refused_before_motion(cell: tuple[AppCell, dict[str, Any]],
                                                             body: dict[str, Any], field: str) -> None:
    served, _ = cell
    with served.http() as http:
        before = http.get("/robots/robot0/state").json()["pose_ur"]
        r = http.post("/robots/robot0/move", json=body)
        assert 400 <= r.status_code < 500 and r.status_code != 409, r.text
        assert field in strict_json(r.text)["error"]["message"]
        after = http.get("/robots/robot0/state").json()["pose_ur"]
        assert after == pytest.approx(before, abs=1e-9)  # nothing moved
        assert http.get("/robots/robot0/motion").json()["owner"] is None


def test_a_deep_non_finite_number_is_named_by_its_path(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, _ = cell
    doc = {"recipe_id": 43, "recipe": {"name": "x", "models": [{"levels": [{"points": [[1.0, 2.0], [3.0, "@"]]}]}]}}
    text = json.dumps(doc).replace('"@"', "-Infinity")
    with served.http() as http:
        msg = refused(raw_post(http, "/recipes", text), "body.recipe.models.0.levels.0.points.1.1")
        assert "-Infinity" in msg


def test_a_non_finite_number_deep_in_a_large_body_is_named(cell: tuple[AppCell, dict[str, Any]]) -> None:
    served, _ = cell
    points = [[float(i), float(i) + 0.5] for i in range(40_000)]  # ~1 MB of JSON: checked off the event loop
    doc = {"recipe_id": 44, "recipe": {"name": "big", "models": [{"points": points + [[1.0, "@"]]}]}}
    text = json.dumps(doc).replace('"@"', "NaN")
    assert len(text) > 500_000
    with served.http() as http:
        refused(raw_post(http, "/recipes", text), f"body.recipe.models.0.points.{len(points)}.1")
        assert http.get("/recipes/44").status_code == 404
