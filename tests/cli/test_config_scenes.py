"""``cellctl config default --scene NAME``: each built-in scene's cell.yaml validates, and the
fixed-camera cell is an eye-to-hand cell whose camera is fixed (jog-to-mark's tool centre is accepted)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.config import load_config
from tests.support.app import in_process_cell
from tests.support.cli import run_cli


@pytest.mark.parametrize("scene,cell_id", [("virtual-cell", "virtual-cell"), ("production", "production-cell"),
                                           ("fixed-camera", "fixed-camera-cell")])
def test_each_scene_prints_a_valid_config(tmp_path: Path, scene: str, cell_id: str) -> None:
    r = run_cli("config", "default", "--scene", scene)
    assert r.returncode == 0, r.stderr
    path = tmp_path / "cell.yaml"
    path.write_text(r.stdout)
    cfg = load_config(path)
    assert cfg.cell_id == cell_id
    if scene != "production":
        assert "home" in cfg.robots["robot0"].poses


def test_the_fixed_camera_cell_serves_a_fixed_camera(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(run_cli("config", "default", "--scene", "fixed-camera").stdout)
    with in_process_cell(tmp_path, path) as a, a.http() as http:
        truth = http.get("/sim/truth").json()
        assert "T_base_cam" in truth and truth["T_base_cam"][2][3] == pytest.approx(0.46, abs=1e-6)
        assert http.post("/robots/robot0/move", json={"named_pose": "over_plate", "speed_m_s": 0.25}).status_code == 200
        r = http.post("/routines/jog-to-mark", json={"tool_centre": True, "marks": 4})
        assert r.status_code == 202, r.text  # a fixed camera: the tool-centre step is accepted here
        assert http.delete(f"/jobs/{r.json()['id']}").status_code == 200
