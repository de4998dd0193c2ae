"""Named poses in cell.yaml (robots.<id>.poses), the move to one over REST, and the 422 on an
unknown key listing the keys that are accepted there (bodies and routine parameters)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from cellctl.config import ConfigError, default_config_text, parse_config
from tests.support.app import AppCell, in_process_cell


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppCell]:
    with in_process_cell(tmp_path_factory.mktemp("poses")) as a:
        yield a


def _cfg_with_pose(pose: object) -> dict:
    data = yaml.safe_load(default_config_text())
    data["robots"]["robot0"]["poses"] = {"p": pose}
    return data


def test_the_default_cell_names_home_and_the_robots_route_lists_it(app: AppCell) -> None:
    robots = app.client.get("/robots", headers=app.auth()).json()
    assert robots[0]["poses"]["home"] == [0.4, 0.0, 0.55, 3.14159265, 0.0, 0.0]


@pytest.mark.parametrize("pose,words", [
    ([0.4, 0.0, 0.55, 3.14159265, 0.0], "6"),            # five numbers
    ([0.05, 0.0, 0.55, 3.14159265, 0.0, 0.0], "x = 50.0 mm is outside the workspace envelope"),
    ([400.0, 0.0, 550.0, 3.14159265, 0.0, 0.0], "metres"),  # millimetres where metres belong
    ([0.4, 0.0, 0.55, 0.0, 0.0, 0.0], "from pointing down"),
    ([0.4, 0.0, 0.55, 30.0, 0.0, 0.0], "radians"),
])
def test_a_bad_named_pose_is_refused_at_start_up(pose: object, words: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(_cfg_with_pose(pose))
    assert "robots.robot0" in str(err.value) and words in str(err.value), str(err.value)


def test_move_to_a_named_pose_and_back(app: AppCell) -> None:
    r = app.client.post("/robots/robot0/move", json={"named_pose": "side", "speed_m_s": 0.25}, headers=app.auth())
    assert r.status_code == 200, r.text
    assert r.json()["pose_ur"]["x_m"] == pytest.approx(0.45, abs=1e-4)
    assert r.json()["pose_ur"]["y_m"] == pytest.approx(0.1, abs=1e-4)
    r = app.client.post("/robots/robot0/move", json={"named_pose": "home", "speed_m_s": 0.25}, headers=app.auth())
    assert r.status_code == 200 and r.json()["pose_ur"]["y_m"] == pytest.approx(0.0, abs=1e-4)
    audit = app.client.get("/audit", params={"action": "robot.move"}, headers=app.auth())
    assert any("named_pose home" in str(e) for e in audit.json())  # the audit log names the pose


def test_an_unknown_pose_name_lists_the_named_ones(app: AppCell) -> None:
    r = app.client.post("/robots/robot0/move", json={"named_pose": "hme"}, headers=app.auth())
    assert r.status_code == 422
    err = r.json()["error"]
    assert err["code"] == "unknown_pose" and "home, side" in err["message"]


def test_two_targets_at_once_are_refused_naming_both(app: AppCell) -> None:
    body = {"named_pose": "home", "pose_ur": {"x_m": 0.4, "y_m": 0, "z_m": 0.5, "rx_rad": 3.14, "ry_rad": 0,
                                               "rz_rad": 0}}
    r = app.client.post("/robots/robot0/move", json=body, headers=app.auth())
    assert r.status_code == 422 and "pose_ur and named_pose" in r.json()["error"]["message"]


def test_an_unknown_key_lists_the_accepted_keys(app: AppCell) -> None:
    r = app.client.post("/robots/robot0/move", json={"x_mm": 400}, headers=app.auth())
    assert r.status_code == 422
    assert r.json()["error"]["message"] == ("body.x_mm: unknown key (accepted: T_base_tool, pose_ur, named_pose, "
                                            "speed_m_s)")
    r = app.client.post("/robots/robot0/move", json={"pose_ur": {"x_m": 0.4, "y_m": 0, "z_m": 0.5, "rx_rad": 3.14,
                                                                 "ry_rad": 0, "rz_rad": 0, "speed": 1}},
                        headers=app.auth())
    assert r.status_code == 422
    assert "body.pose_ur.speed: unknown key (accepted: x_m, y_m, z_m, rx_rad, ry_rad, rz_rad)" in r.text
    r = app.client.post("/calibrations/1/activate", json={"forced": True}, headers=app.auth())
    assert r.status_code == 422 and "body.forced: unknown key (accepted: force)" in r.text


def test_an_unknown_key_in_a_tagged_section_lists_that_kind_s_keys(app: AppCell) -> None:
    place = {"kind": "grid", "origin_ur": [0.4, 0, 0.1, 3.14, 0, 0], "rows": 2, "cols": 2, "pitch_mm": [10, 10],
             "pitch": 1}
    r = app.client.post("/recipes", json={"recipe_id": 1, "recipe": {"name": "x", "models": [], "plane_z_mm": 0,
                                                                      "place": place}}, headers=app.auth())
    assert r.status_code == 422
    assert ("body.recipe.place.grid.pitch: unknown key (accepted: kind, origin_ur, rows, cols, pitch_mm, layers, "
            "layer_mm, approach_height_mm)") in r.json()["error"]["message"]
    r = app.client.post("/production/start", json={"recipe_id": 1, "cnt": 2}, headers=app.auth())
    assert r.status_code == 422 and "body.cnt: unknown key (accepted: recipe_id, count," in r.text


def test_an_unknown_routine_parameter_lists_the_parameters(app: AppCell) -> None:
    r = app.client.post("/routines/verify", json={"tolerance": 2}, headers=app.auth())
    assert r.status_code == 422
    msg = r.json()["error"]["message"]
    assert "tolerance: unknown key (accepted: camera_id, robot_id, target, tolerance_px, tolerance_mm)" in msg


def test_accepted_keys_walks_lists_dicts_and_unions(tmp_path: Path) -> None:
    from typing import Annotated

    from pydantic import BaseModel, Field

    from cellctl.errors_format import accepted_keys

    class Inner(BaseModel):
        a: int
        b_mm: float

    class Outer(BaseModel):
        items: list[Inner] = []
        by_name: dict[str, Inner] = {}
        maybe: Annotated[Inner | None, Field(None)] = None

    assert accepted_keys(Outer, ()) == ["items", "by_name", "maybe"]
    assert accepted_keys(Outer, ("items", 3)) == ["a", "b_mm"]
    assert accepted_keys(Outer, ("by_name", "x")) == ["a", "b_mm"]
    assert accepted_keys(Outer, ("maybe",)) == ["a", "b_mm"]
    assert accepted_keys(Outer, ("nothing",)) is None


def test_an_unknown_key_in_cell_yaml_lists_the_accepted_keys() -> None:
    data = yaml.safe_load(default_config_text())
    data["robots"]["robot0"]["pose"] = {"home": [0.4, 0.0, 0.55, 3.14159265, 0.0, 0.0]}
    with pytest.raises(ConfigError) as err:
        parse_config(data)
    assert "robots.robot0.pose: unknown key (accepted: kind, settings, envelope," in str(err.value)
    assert "poses)" in str(err.value)
    data = yaml.safe_load(default_config_text())
    data["cameras"]["cam0"]["settings"]["colour"] = "red"
    with pytest.raises(ConfigError, match=r"cameras\.cam0\.settings\.colour: unknown key \(accepted: scene, "):
        parse_config(data)
