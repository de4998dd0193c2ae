"""The Stop latch outlives the service: ``cellctl serve`` killed (-9) or stopped (SIGTERM) and started
again on the same store keeps a latched robot latched until an engineer resumes it.

Real served cells with the virtual robot (moves scaled to a tenth of real time: the restart is the
point here, not the motion), a real HTTP client, tokens of each role.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text
from cellctl.store import Store
from tests.support.served import Served, start_served, stop_served

AWAY = {"x_m": 0.42, "y_m": 0.02, "z_m": 0.50, "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}


class Cell:
    """A cell.yaml with its store and tokens, served again and again from the same data dir."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.config = tmp / "cell.yaml"
        data = yaml.safe_load(default_config_text())
        data["store"] = {"path": str(tmp / "cell.db")}
        data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.1
        self.config.write_text(yaml.safe_dump(data))
        self.tokens: dict[str, str] = {}
        for role in ("operator", "engineer"):
            out = tmp / f"{role}.json"
            assert main(["token", "add", "--config", str(self.config), "--name", f"{role}-1", "--role", role,
                         "--out", str(out)]) == 0
            self.tokens[role] = json.loads(out.read_text())["token"]
        self.served: Served | None = None

    def start(self) -> httpx.Client:
        """Serve the cell (the engineer's client)."""
        self.served = start_served(self.tmp, config=self.config, token=self.tokens["engineer"])
        return self.served.client(timeout_s=30)

    def operator(self) -> httpx.Client:
        assert self.served is not None
        return self.served.client(token=self.tokens["operator"], timeout_s=30)

    def kill_9(self) -> None:
        assert self.served is not None
        self.served.process.kill()  # SIGKILL: no shutdown code runs
        self.served.process.wait(timeout=15)
        self.served = None

    def terminate(self) -> None:
        assert self.served is not None
        stop_served(self.served)  # SIGTERM: the clean shutdown
        self.served = None


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[Cell]:
    c = Cell(tmp_path)
    try:
        yield c
    finally:
        if c.served is not None:
            stop_served(c.served)


def _stop(cell: Cell) -> dict[str, Any]:
    with cell.operator() as op:
        r = op.post("/robots/robot0/stop")
    assert r.status_code == 200, r.text
    body = dict(r.json())
    assert body["latched"] and body["latch_stored"], body
    return body


def _assert_latched(http: httpx.Client, by: str) -> None:
    state = http.get("/robots/robot0/state")
    assert state.status_code == 200 and state.json()["latched"] is True, state.text
    motion = http.get("/robots/robot0/motion").json()
    assert (motion["latched_by"], motion["latched_reason"]) == (by, "Stop")
    r = http.post("/robots/robot0/move", json={"pose_ur": AWAY, "speed_m_s": 0.1})
    assert r.status_code == 409 and r.json()["error"]["code"] == "robot_stopped", r.text


def test_a_latch_survives_kill_9_and_the_resume_survives_it_too(cell: Cell) -> None:
    with cell.start():
        stopped = _stop(cell)
    cell.kill_9()
    with cell.start() as http:
        _assert_latched(http, "operator-1")
        assert http.get("/robots/robot0/motion").json()["latched_since_s"] == stopped["latched_since_s"]
        carried = http.get("/audit", params={"action": "robot.latch", "limit": 1}).json()[0]
        assert carried["target"] == "robot0"
        assert carried["result"].startswith("latched at start: stopped before the restart at ")
        assert carried["result"].endswith(" by operator-1 (Stop)")
        r = http.post("/robots/robot0/resume")
        assert r.status_code == 200 and r.json()["resumed"] and r.json()["latch_stored"], r.text
    cell.kill_9()
    with cell.start() as http:
        assert http.get("/robots/robot0/state").json()["latched"] is False
        r = http.post("/robots/robot0/move", json={"pose_ur": AWAY, "speed_m_s": 0.1})
        assert r.status_code == 200, r.text
        entries = http.get("/audit", params={"action": "robot.latch", "limit": 10}).json()[::-1]
        assert [(e["who"], e["detail"]["latched"]) for e in entries] == [
            ("operator-1", True), ("operator-1", True), ("engineer-1", False)]  # Stop, carried over, resumed


def test_a_latch_survives_a_clean_restart(cell: Cell) -> None:
    with cell.start():
        _stop(cell)
    cell.terminate()
    # The row a restart reads is in the cell's store file.
    with Store(f"sqlite:///{cell.tmp / 'cell.db'}", "virtual-cell") as store:
        assert [(x.robot_id, x.latched_by, x.reason) for x in store.latches()] == [("robot0", "operator-1", "Stop")]
    with cell.start() as http:
        _assert_latched(http, "operator-1")
