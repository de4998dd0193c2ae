"""An in-process cell starts on a fresh virtual cell, as a new ``cellctl serve`` does (tests/support/app.py).

The virtual cell's camera rides on its robot: a cell that moved the robot left the next in-process
cell of the same xdist worker looking elsewhere, and the README's teach ROI showed no part (a CI run
with 6 workers failed ``test_recipe_audit.py`` so)."""

from __future__ import annotations

from pathlib import Path

from tests.support.app import in_process_cell


def test_a_robot_moved_by_one_in_process_cell_is_home_in_the_next(tmp_path: Path) -> None:
    with in_process_cell(tmp_path / "a") as a:
        moved = a.client.post("/robots/robot0/move", headers=a.auth(), json={"named_pose": "side", "speed_m_s": 0.25})
        assert moved.status_code == 200, moved.text
    with in_process_cell(tmp_path / "b") as b:
        taught = b.client.post("/pick/teach", headers=b.auth(), json={"roi": [906, 141, 200, 200], "name": "bracket"})
        assert taught.status_code == 200, taught.text
