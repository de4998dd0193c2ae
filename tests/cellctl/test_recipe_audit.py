"""A recipe save is audited once (by the store, in the save's own transaction), not twice."""

from __future__ import annotations

from pathlib import Path

from tests.support.app import in_process_cell


def test_a_recipe_save_is_audited_once(tmp_path: Path) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        part = http.post("/pick/teach", json={"roi": [906, 141, 200, 200], "name": "bracket"})
        assert part.status_code == 200, part.text
        recipe = {"name": "bracket", "models": [part.json()],
                  "plane_z_mm": 0.0, "grasp_z_mm": 5.0}
        for version in (1, 2):
            r = http.post("/recipes", json={"recipe_id": 7, "recipe": recipe})
            assert r.status_code == 201 and r.json()["version"] == version, r.text
        saves = http.get("/audit", params={"action": "recipe.save"}).json()
    assert [(e["target"], e["detail"]["version"]) for e in saves if "7" in e["target"]] in (
        [("recipe:7", 1), ("recipe:7", 2)], [("recipe:7", 2), ("recipe:7", 1)])
