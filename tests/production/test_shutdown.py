"""A service that stops with a production run in progress ends the run: the robot halted (not
latched), the run ``stopped`` with the reason, its records written, a held part still gripped."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from fastapi import FastAPI

from cellctl.production.manager import existing_manager
from drivers.sim.world import world_for
from tests.support.app import in_process_cell
from tests.support.production_cell import production_config, teach_recipe


@pytest.mark.slow  # an in-process production cell moving at half speed, twice: ~13 s
def test_the_service_stopping_mid_run_stops_the_run_halted_and_recorded(tmp_path: Path) -> None:
    config = production_config(tmp_path, count=4, time_scale=0.5)
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        teach_recipe(http)
        r = http.post("/production/start", json={"recipe_id": 1})
        assert r.status_code == 202, r.text
        run_id = r.json()["run_id"]
        deadline = time.monotonic() + 60
        while not any(p["state"] == "held" for p in http.get("/sim/truth").json()["parts"]):
            assert time.monotonic() < deadline, "no part was ever held"
            time.sleep(0.02)
        app = cell.client.app
        assert isinstance(app, FastAPI)
        manager = existing_manager(app.state.services)
        assert manager is not None
        run = manager.run()
        assert not run.ended
    # The lifespan has ended: the run with it, before the devices closed.
    assert run.ended and run.status.state == "stopped" and run.status.ended_because == "stopped"
    assert run.status.stop_reason is not None and "shutting down" in run.status.stop_reason
    assert not run.robot.motion.latched  # halted, not latched: the next service may move it at once
    world = world_for(tmp_path / "scene.yaml")
    states = [p["state"] for p in world.truth()["parts"]]
    assert states.count("held") == 1, states  # the gripper kept the part
    T0 = np.array(world.T_base_tool_true)
    time.sleep(0.3)
    assert np.allclose(world.T_base_tool_true, T0), "the robot still moves after the service stopped"

    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        st = http.get("/production").json()
        assert st["run_id"] == run_id and st["state"] == "stopped" and st["ended_because"] == "stopped", st
        assert "shutting down" in st["stop_reason"], st
        records = http.get(f"/production/runs/{run_id}/cycles").json()
        assert records and records[-1]["result"] == "stopped" and "shutting down" in records[-1]["detail"]
        assert [r["result"] for r in records].count("placed") == st["counters"]["placed"]
        assert http.get("/robots/robot0/motion").json()["latched"] is False
        refused = http.post("/production/start", json={"recipe_id": 1})
        assert refused.status_code == 409 and refused.json()["error"]["code"] == "gripper_holding", refused.text
