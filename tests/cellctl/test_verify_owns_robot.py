"""verify owns the robot: refused (409 robot_busy) while another caller moves it, run once it is free.

A served built-in cell with the real-time virtual robot (the move must really be under way) and
the true camera calibration active; a real HTTP client with an operator's and an engineer's token.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text, parse_config
from cellctl.store import open_store
from drivers.sim.world import forget_worlds, world_for
from tests.support.served import Served, start_served, stop_served

HOME = {"x_m": 0.40, "y_m": 0.0, "z_m": 0.55, "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}
NEAR = {**HOME, "z_m": 0.50}


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("verify-owns")
    cfg = tmp / "cell.yaml"
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    cfg.write_text(yaml.safe_dump(data))
    tokens: dict[str, str] = {}
    for role in ("operator", "engineer"):
        out = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-1", "--role", role,
                     "--out", str(out)]) == 0
        tokens[role] = json.loads(out.read_text())["token"]
    forget_worlds()
    truth = world_for(None, None).truth()
    forget_worlds()
    with open_store(parse_config(data)) as store:
        cam = store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="test", note="truth")
        store.activate(cam.id, "test")
    served = start_served(tmp, config=cfg, token=tokens["engineer"])
    try:
        yield served, tokens
    finally:
        stop_served(served)


def _wait(http: httpx.Client, path: str, done: Any, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        body = http.get(path).json()
        if done(body):
            return dict(body)
        time.sleep(0.02)
    raise AssertionError(f"{path} did not reach the awaited state")


def test_verify_is_refused_while_another_caller_moves_the_robot_and_runs_once_it_is_free(
        cell: tuple[Served, dict[str, str]]) -> None:
    served, tokens = cell
    with served.client(timeout_s=60) as eng, served.client(token=tokens["operator"], timeout_s=60) as op:
        answers: list[httpx.Response] = []
        mover = threading.Thread(target=lambda: answers.append(
            eng.post("/robots/robot0/move", json={"pose_ur": NEAR, "speed_m_s": 0.025})), daemon=True)  # 2 s
        mover.start()
        _wait(op, "/robots/robot0/state", lambda s: s["moving"], timeout_s=20)
        r = op.post("/routines/verify", json={})
        assert r.status_code == 409 and r.json()["error"]["code"] == "robot_busy", r.text
        assert "linear move" in r.json()["error"]["message"]  # names what owns the robot
        assert not [j for j in op.get("/jobs").json() if j["name"] == "verify"]  # it did not run
        mover.join(30)
        assert answers and answers[0].status_code == 200, answers
        back = eng.post("/robots/robot0/move", json={"pose_ur": HOME, "speed_m_s": 0.25})
        assert back.status_code == 200, back.text

        r = op.post("/routines/verify", json={})
        assert r.status_code == 202, r.text
        job = _wait(op, f"/jobs/{r.json()['id']}", lambda j: j["state"] != "running")
        assert job["state"] == "succeeded", job
        assert job["result"]["passed"] is True
        assert op.get("/robots/robot0/motion").json()["owner"] is None  # released when it ended


def test_verify_runs_while_the_robot_is_latched_and_holds_it_still(cell: tuple[Served, dict[str, str]]) -> None:
    """A latched robot stands still: verify measures (PLC verify works while latched too)."""
    served, tokens = cell
    with served.client(timeout_s=60) as eng, served.client(token=tokens["operator"], timeout_s=60) as op:
        assert op.post("/robots/robot0/stop").status_code == 200
        try:
            r = op.post("/routines/verify", json={})
            assert r.status_code == 202, r.text
            job = _wait(op, f"/jobs/{r.json()['id']}", lambda j: j["state"] != "running")
            assert job["state"] == "succeeded" and job["result"]["passed"] is True, job
            assert op.get("/robots/robot0/motion").json()["latched"] is True  # verify never resumes it
        finally:
            assert eng.post("/robots/robot0/resume").status_code == 200
