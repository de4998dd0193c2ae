"""Stop, resume and the motion owner on ``cellctl serve`` with the real-time virtual robot.

A served built-in cell (the robot moves in real time, as a real arm), the true calibrations and
a taught part stored before start, tokens of every role; a real HTTP client. Each test leaves the
robot resumed and back home. Waits are on the robot's reported state, never on fixed sleeps.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text, parse_config
from cellctl.pick.model import teach
from cellctl.pick.recipe import Recipe
from cellctl.store import open_store
from drivers.sim.world import forget_worlds, world_for
from tests.conftest import Served, start_served, stop_served
from tests.support.truth import activate_truth

HOME = {"x_m": 0.40, "y_m": 0.0, "z_m": 0.55, "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}
LOW = {**HOME, "z_m": 0.30}


def _prepare_store(cfg: Path) -> None:
    """The virtual cell's true camera and hand-eye, activated, and recipe 1 (the bracket)."""
    config = parse_config(yaml.safe_load(cfg.read_text()))
    forget_worlds()
    world = world_for(None, None)
    truth = world.truth()
    with open_store(config) as store:
        activate_truth(store, truth, "eye-in-hand", np.eye(4))
        part = world.scene.parts[0]
        T_cam_base = np.linalg.inv(world.T_base_cam())
        p = T_cam_base @ np.array([part.x_mm * 1e-3, part.y_mm * 1e-3, 0.0, 1.0])
        u, v = world.camera_model.project(p[None, :3])[0]
        model = teach(world.render(), (u - 100, v - 100, 200, 200), mode="shape", name="bracket")
        recipe = Recipe(name="bracket", models=[model.to_dict()], plane_z_mm=0.0, grasp_z_mm=5.0,
                        approach_height_mm=40.0, speed_m_s=0.05)
        store.save_recipe(1, "bracket", recipe.model_dump(mode="json"), "test")
    forget_worlds()


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("motion")
    cfg = tmp / "cell.yaml"
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    cfg.write_text(yaml.safe_dump(data))
    tokens: dict[str, str] = {}
    for role in ("viewer", "operator", "engineer"):
        out = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-1", "--role", role,
                     "--out", str(out)]) == 0
        tokens[role] = json.loads(out.read_text())["token"]
    _prepare_store(cfg)
    served = start_served(tmp, config=cfg, token=tokens["engineer"])
    try:
        yield served, tokens
    finally:
        stop_served(served)


@pytest.fixture()
def http(cell: tuple[Served, dict[str, str]]) -> Iterator[httpx.Client]:
    served, _ = cell
    with served.client(timeout_s=60) as client:
        yield client
        client.post("/robots/robot0/resume")
        r = client.post("/robots/robot0/move", json={"pose_ur": HOME, "speed_m_s": 0.25})
        assert r.status_code == 200, r.text


def _as(cell: tuple[Served, dict[str, str]], role: str) -> httpx.Client:
    served, tokens = cell
    return served.client(token=tokens[role], timeout_s=60)


class _Call:
    """One HTTP request in a thread (a long move or pick), its response kept."""

    def __init__(self, fn: Callable[[], httpx.Response]) -> None:
        self.response: httpx.Response | None = None
        self._t = threading.Thread(target=self._run, args=(fn,), daemon=True)
        self._t.start()

    def _run(self, fn: Callable[[], httpx.Response]) -> None:
        self.response = fn()

    def result(self, timeout_s: float = 60.0) -> httpx.Response:
        self._t.join(timeout_s)
        assert self.response is not None, "the request did not answer"
        return self.response


def _wait_moving(http: httpx.Client, timeout_s: float = 20.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = http.get("/robots/robot0/state").json()
        if s["moving"]:
            return dict(s)
        time.sleep(0.02)
    raise AssertionError("the robot never moved")


def _wait_job(http: httpx.Client, job_id: str, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = http.get(f"/jobs/{job_id}").json()
        if job["state"] != "running":
            return dict(job)
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not end")


def _z_m(http: httpx.Client) -> float:
    return float(http.get("/robots/robot0/state").json()["pose_ur"]["z_m"])


def test_stop_during_a_move_halts_it_and_latches_until_an_engineer_resumes(
        cell: tuple[Served, dict[str, str]], http: httpx.Client) -> None:
    move = _Call(lambda: http.post("/robots/robot0/move", json={"pose_ur": LOW, "speed_m_s": 0.05}))  # 5 s
    _wait_moving(http)
    deadline = time.monotonic() + 10
    while _z_m(http) > 0.545 and time.monotonic() < deadline:  # well on its way
        time.sleep(0.02)
    with _as(cell, "viewer") as viewer:
        assert viewer.post("/robots/robot0/stop").status_code == 403
    with _as(cell, "operator") as operator:
        r = operator.post("/robots/robot0/stop")
        assert r.status_code == 200, r.text
        assert r.json()["latched"] and r.json()["aborted"].startswith("linear move")
        answer = move.result()
        assert answer.status_code == 409 and answer.json()["error"]["code"] == "robot_stopped", answer.text
        z_stop = _z_m(http)
        assert 0.31 < z_stop < 0.549  # halted on the way
        assert http.get("/robots/robot0/state").json()["latched"]
        r = http.post("/robots/robot0/move", json={"pose_ur": HOME, "speed_m_s": 0.25})
        assert r.status_code == 409 and r.json()["error"]["code"] == "robot_stopped"
        assert "resume" in r.json()["error"]["message"]
        assert operator.post("/robots/robot0/resume").status_code == 403  # an operator cannot resume
    assert abs(_z_m(http) - z_stop) < 1e-3  # nothing moved it while latched
    r = http.post("/robots/robot0/resume")
    assert r.status_code == 200 and r.json()["resumed"] and not r.json()["latched"]
    audit = http.get("/audit", params={"limit": 10}).json()
    actions = [(a["action"], a["result"].split(":")[0]) for a in audit]
    assert ("robot.resume", "ok") in actions and ("robot.stop", "ok") in actions
    assert ("robot.move", "stopped") in actions  # the halted move is audited as stopped, never "ok"


def test_a_second_move_while_one_runs_is_refused_busy(http: httpx.Client) -> None:
    first = _Call(lambda: http.post("/robots/robot0/move", json={"pose_ur": LOW, "speed_m_s": 0.1}))
    _wait_moving(http)
    r = http.post("/robots/robot0/move", json={"pose_ur": HOME, "speed_m_s": 0.1})
    assert r.status_code == 409 and r.json()["error"]["code"] == "robot_busy", r.text
    assert first.result().status_code == 200
    assert abs(_z_m(http) - LOW["z_m"]) < 1e-3  # the first move arrived where it was sent


def test_stop_during_a_pick_with_move_aborts_the_pick(cell: tuple[Served, dict[str, str]],
                                                      http: httpx.Client) -> None:
    pick = _Call(lambda: http.post("/pick", json={"recipe_id": 1, "move": True}))
    moving = _wait_moving(http)
    with _as(cell, "operator") as operator:
        assert operator.post("/robots/robot0/stop").status_code == 200
    answer = pick.result()
    assert answer.status_code == 409 and answer.json()["error"]["code"] == "robot_stopped", answer.text
    assert _z_m(http) > 0.04  # it never came down to the pick height (5 mm)
    assert moving["pose_ur"]["z_m"] > 0.04
    moves = http.get("/audit", params={"limit": 5, "action": "robot.move"}).json()
    assert moves[0]["detail"]["why"] == "pick approach" and moves[0]["result"].startswith("stopped")
    r = http.post("/pick", json={"recipe_id": 1, "move": True})
    assert r.status_code == 409 and r.json()["error"]["code"] == "robot_stopped"  # latched: no new pick


@pytest.mark.parametrize("routine", ["intrinsics-capture", "handeye-capture"])
def test_stop_during_a_moving_routine_ends_it_stopped_and_stores_nothing(
        cell: tuple[Served, dict[str, str]], http: httpx.Client, routine: str) -> None:
    before = len(http.get("/calibrations").json())
    r = http.post(f"/routines/{routine}", json={})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    _wait_moving(http)
    with _as(cell, "operator") as operator:
        assert operator.post("/robots/robot0/stop").status_code == 200
    job = _wait_job(http, job_id)
    assert job["state"] == "stopped", job
    assert "Stop" in job["message"] and "nothing was stored" in job["message"]
    z = _z_m(http)
    time.sleep(0.3)
    assert abs(_z_m(http) - z) < 1e-4  # the routine did not go on to its next station
    assert len(http.get("/calibrations").json()) == before
    r = http.post(f"/routines/{routine}", json={})
    assert r.status_code == 409 and r.json()["error"]["code"] == "robot_stopped"


def test_one_motion_owner_for_routines_moves_and_picks(http: httpx.Client) -> None:
    r = http.post("/routines/intrinsics-capture", json={})
    assert r.status_code == 202
    job_id = r.json()["id"]
    try:
        for path, body in (("/routines/handeye-capture", {}), ("/routines/intrinsics-capture", {}),
                           ("/robots/robot0/move", {"pose_ur": HOME, "speed_m_s": 0.1}),
                           ("/pick", {"recipe_id": 1, "move": True})):
            r = http.post(path, json=body)
            assert r.status_code == 409 and r.json()["error"]["code"] == "robot_busy", (path, r.text)
        # Looking needs no motion, but this cell's camera rides on the arm: a frame taken while the routine
        # moves it would be paired with the wrong pose, so locating waits for the robot (issue 21 item 5).
        r = http.post("/pick", json={"recipe_id": 1})
        assert r.status_code == 409 and r.json()["error"]["code"] == "robot_busy", r.text
    finally:
        http.delete(f"/jobs/{job_id}")
        assert _wait_job(http, job_id)["state"] == "cancelled"
    r = http.get("/robots/robot0/motion").json()
    assert r["owner"] is None and not r["latched"]
    assert http.post("/pick", json={"recipe_id": 1}).status_code == 200  # the robot free: located as before


@pytest.mark.parametrize(("body", "field"), [
    ({"pose_ur": HOME, "speed_m_s": 1e-6}, "use at least"),
    ({"pose_ur": {**HOME, "rx_rad": 0.0}, "speed_m_s": 0.1}, "pointing down"),
])
def test_moves_that_cannot_be_supervised_are_refused(http: httpx.Client, body: dict[str, Any], field: str) -> None:
    r = http.post("/robots/robot0/move", json={**body, "pose_ur": {**body["pose_ur"], "z_m": 0.5}})
    assert r.status_code == 422 and field in r.json()["error"]["message"], r.text
