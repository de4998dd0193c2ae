"""Recipes like calibrations over REST: every save a new version, the versions listed, a roll back that
stores the old version's data as the newest, duplicate under a new number, delete (engineer, audited,
refused while a production run uses the recipe)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.support.app import in_process_cell
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def part(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    with in_process_cell(tmp_path_factory.mktemp("teach")) as a, a.http() as http:
        r = http.post("/pick/teach", json={"roi": [906, 141, 200, 200], "name": "bracket"})
        assert r.status_code == 200, r.text
        return dict(r.json())


def _recipe(part: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"name": "bracket", "models": [part], "plane_z_mm": 0.0, "grasp_z_mm": 5.0, **extra}


def test_versions_roll_back_duplicate_delete(tmp_path: Path, part: dict[str, Any]) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        for min_score in (0.6, 0.8):
            r = http.post("/recipes", json={"recipe_id": 4, "recipe": _recipe(part, search={"min_score": min_score})})
            assert r.status_code == 201, r.text
        versions = http.get("/recipes/4/versions").json()
        assert [(v["version"], v["active"]) for v in versions] == [(2, True), (1, False)]
        assert http.get("/recipes/4/versions/1").json()["data"]["search"]["min_score"] == 0.6

        back = http.post("/recipes/4/versions/1/activate")
        assert back.status_code == 200, back.text
        assert back.json()["version"] == 3 and back.json()["from_version"] == 1
        assert http.get("/recipes/4").json()["data"]["search"]["min_score"] == 0.6  # version 1's data in force
        assert len(http.get("/recipes/4/versions").json()) == 3  # nothing rewritten
        assert http.post("/recipes/4/versions/9/activate").status_code == 404

        dup = http.post("/recipes/4/duplicate", json={"new_recipe_id": 5, "name": "bracket copy"})
        assert dup.status_code == 201, dup.text
        assert dup.json()["version"] == 1 and http.get("/recipes/5").json()["name"] == "bracket copy"
        again = http.post("/recipes/4/duplicate", json={"new_recipe_id": 5})
        assert again.status_code == 409 and again.json()["error"]["code"] == "recipe_exists"

        listed = {r["recipe_id"]: r for r in http.get("/recipes").json()}
        assert listed[4]["version"] == 3 and listed[4]["place"] is None and listed[4]["gripper_device"] is None

        gone = http.delete("/recipes/5")
        assert gone.status_code == 200 and gone.json()["deleted_versions"] == 1
        assert http.get("/recipes/5").status_code == 404
        assert http.delete("/recipes/5").status_code == 404
        audit = http.get("/audit", params={"limit": 50}).json()
        actions = {(e["action"], e["target"]) for e in audit}
        assert {("recipe.activate", "recipe:4"), ("recipe.duplicate", "recipe:5"),
                ("recipe.delete", "recipe:5")} <= actions
        deleted = next(e for e in audit if e["action"] == "recipe.delete")
        assert deleted["who"] == "session" and deleted["detail"]["name"] == "bracket copy"


def test_recipe_management_needs_an_engineer(tmp_path: Path, part: dict[str, Any]) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(run_cli("config", "default").stdout)
    tokens = {role: json.loads(run_cli("token", "add", "--config", str(cfg), "--name", role[:3], "--role", role
                                       ).stdout)["token"] for role in ("operator", "engineer")}
    with in_process_cell(tmp_path, cfg, token=tokens["engineer"]) as a, a.http() as http:
        assert http.post("/recipes", json={"recipe_id": 2, "recipe": _recipe(part)}).status_code == 201
        with a.http(tokens["operator"]) as as_operator:
            assert as_operator.get("/recipes/2/versions").status_code == 200
            for method, path in (("POST", "/recipes/2/versions/1/activate"), ("DELETE", "/recipes/2"),
                                 ("POST", "/recipes/2/duplicate")):
                r = as_operator.request(method, path, json={"new_recipe_id": 3} if "duplicate" in path else None)
                assert r.status_code == 403, (path, r.text)


def test_a_grip_wider_than_the_stroke_is_refused_with_the_reason(tmp_path: Path, part: dict[str, Any]) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        gripper = {"grip_width_mm": 90.0, "device": {"io_id": "gripper0", "kind": "robotiq_2f", "stroke_mm": 85.0}}
        r = http.post("/recipes", json={"recipe_id": 3, "recipe": _recipe(part, gripper=gripper)})
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_grasp", r.text
        assert "grip_width_mm 90 mm is wider than the gripper's stroke" in r.json()["error"]["message"]
        gripper["grip_width_mm"] = 30.0
        assert http.post("/recipes", json={"recipe_id": 3, "recipe": _recipe(part, gripper=gripper)}).status_code == 201
