"""``cellctl config default --motion-time-scale S``: the printed cell's sim robot (and sim gripper)
move S times real time; everything else, comments included, is printed as without it."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.config import load_config
from tests.support.cli import run_cli


@pytest.mark.parametrize("scene", ["virtual-cell", "production"])
def test_the_scale_lands_in_the_sim_devices_only(tmp_path: Path, scene: str) -> None:
    plain = run_cli("config", "default", "--scene", scene).stdout
    r = run_cli("config", "default", "--scene", scene, "--motion-time-scale", "0.25")
    assert r.returncode == 0, r.stderr
    path = tmp_path / "cell.yaml"
    path.write_text(r.stdout)
    cfg = load_config(path)
    assert cfg.robots["robot0"].settings["motion_time_scale"] == 0.25
    if scene == "production":
        assert cfg.io["gripper0"].settings["time_scale"] == 0.25
    added = [line.strip() for line in r.stdout.splitlines() if line not in plain.splitlines()]
    assert sorted(added) == sorted(["motion_time_scale: 0.25"] + (["time_scale: 0.25"] if scene == "production"
                                                                  else [])), added


@pytest.mark.parametrize("value", ["-1", "11", "fast"])
def test_a_bad_scale_is_a_one_line_error(value: str) -> None:
    r = run_cli("config", "default", "--motion-time-scale", value)
    assert r.returncode != 0 and r.stdout == ""
    assert "--motion-time-scale" in r.stderr and "0-10" in r.stderr, r.stderr
