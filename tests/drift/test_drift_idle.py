"""Idle drift checks on the built-in fixed-camera cell, whose fiducial is the plate fixed on the table (a
target, not marks): the idle thread checks every ``every_s`` while no run uses the camera, a bump of the
camera alarms from those checks, and the thread ends with the service."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cellctl.config import parse_config
from cellctl.store import open_store
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld
from tests.support.app import in_process_cell
from tests.support.forked import run_cellctl
from tests.support.truth import activate_truth


def fixed_camera_cell(tmp: Path) -> Path:
    """``cellctl config default --scene fixed-camera`` with quick idle checks, its true calibrations active."""
    cfg = yaml.safe_load(run_cellctl("config", "default", "--scene", "fixed-camera", check=True).stdout)
    scene = tmp / "scene.yaml"
    scene.write_text(BUILTIN_SCENES["fixed-camera"].read_text())  # a world of its own (not the shared built-in)
    for dev in (cfg["cameras"]["cam0"], cfg["robots"]["robot0"]):
        dev["settings"]["scene"] = str(scene)
    cfg["store"]["path"] = str(tmp / "cell.db")
    cfg["drift"].update({"every_s": 0.2, "baseline_checks": 3})
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    truth = SimWorld(load_scene(scene)).truth()
    with open_store(parse_config(cfg)) as store:
        activate_truth(store, truth, "eye-to-hand", np.eye(4), robot_noise=False)
    return path


def wait_records(http: Any, check: Any, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        body: dict[str, Any] = http.get("/drift").json()
        if check(body):
            return body
        assert time.monotonic() < deadline, body
        time.sleep(0.2)


def test_idle_checks_on_a_fixed_target_catch_a_bump(tmp_path: Path) -> None:
    with in_process_cell(tmp_path, fixed_camera_cell(tmp_path)) as app:
        http = app.http()
        body = wait_records(http, lambda b: b["state"] == "ok")
        idle = [r for r in body["records"] if r["source"] == "idle"]
        assert len(idle) >= 4 and all(r["drift_mm"] < 0.05 and r["seen"] == 49 for r in idle), idle
        assert body["limits"]["ucl_mm"] > body["limits"]["center_mm"]
        assert http.post("/sim/faults", json={"camera_shift_mm": [0.0, 0.5, 0.0]}).status_code == 200
        body = wait_records(http, lambda b: b["state"] == "alarm")
        last = body["records"][-1]
        assert last["source"] == "idle" and last["rule"] == "beyond_3sigma" and abs(last["drift_mm"] - 0.5) < 0.1
        drift = app.client.app.state.services.drift  # type: ignore[attr-defined]
    assert drift._thread is None  # the idle thread was joined when the service closed
