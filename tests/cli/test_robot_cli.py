"""``cellctl robot move|stop|resume|state`` against a running service, and ``robot state --config``
reading the device directly (as before)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from typing import Any

import pytest

from tests.conftest import Served, start_served, stop_served
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("robotcli"))
    try:
        yield s
    finally:
        stop_served(s)


def _robot(served: Served, *args: str, ok: bool = True) -> Any:
    r = run_cli("robot", *args, "--robot", "robot0", "--url", served.base_url, "--token", served.token)
    if not ok:
        return r
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_move_stop_resume_state_on_the_service(served: Served) -> None:
    out = _robot(served, "move", "--named-pose", "side", "--speed-m-s", "0.25")
    assert out["pose_ur"]["x_m"] == pytest.approx(0.45, abs=1e-4)
    out = _robot(served, "move", "--pose-ur", "0.4,0,0.55,3.14159265,0,0", "--speed-m-s", "0.25")
    assert out["pose_ur"]["y_m"] == pytest.approx(0.0, abs=1e-4)
    stopped = _robot(served, "stop")
    assert stopped["stopped"] is True and stopped["latched"] is True
    state = _robot(served, "state")
    assert state["latched"] is True and state["pose_ur"]["x_m"] == pytest.approx(0.4, abs=1e-4)
    refused = _robot(served, "move", "--named-pose", "home", ok=False)
    assert refused.returncode == 2 and "robot_stopped" in refused.stderr and refused.stdout == ""
    resumed = _robot(served, "resume")
    assert resumed["resumed"] is True and resumed["latched"] is False
    assert _robot(served, "state")["latched"] is False


def test_errors_are_one_line(served: Served) -> None:
    r = _robot(served, "move", "--named-pose", "nowhere", ok=False)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "unknown_pose" in r.stderr and "home, side" in r.stderr
    r = _robot(served, "move", "--pose-ur", "400,0,550,3.14,0,0", ok=False)
    assert r.returncode == 2 and "metres" in r.stderr
    r = _robot(served, "move", "--pose-ur", "0.4,0,0.55", ok=False)
    assert r.returncode == 2 and "six numbers" in r.stderr
    r = run_cli("robot", "stop", "--robot", "robot0", "--url", "http://127.0.0.1:9", "--token", "x")
    assert r.returncode == 2 and "cannot reach the service" in r.stderr


def test_state_reads_the_device_only_when_asked_by_name() -> None:
    # Asked by name (--local: the built-in virtual cell; --config FILE likewise): the device, said on stderr.
    r = run_cli("robot", "state", "--robot", "robot0", "--local")
    assert r.returncode == 0, r.stderr
    assert "latched" not in json.loads(r.stdout) and "pose_ur" in json.loads(r.stdout)
    assert "directly, not through a service" in r.stderr
    r = run_cli("robot", "state", "--robot", "robot0", "--local", "--token", "abc")
    assert r.returncode == 2 and "--url" in r.stderr


def test_state_without_url_or_config_asks_the_service(served: Served) -> None:
    """The issue's trip: without --url, `robot state` used to open a private virtual robot and print its
    pose; now it asks the service ($CELLCTL_URL here), like `robot move`, and shows the latch."""
    _robot(served, "move", "--pose-ur", "0.41,0.02,0.52,3.1,0.05,0.05", "--speed-m-s", "0.25")
    env = {**os.environ, "CELLCTL_URL": served.base_url, "CELLCTL_TOKEN": served.token}
    r = run_cli("robot", "state", "--robot", "robot0", env=env)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["latched"] is False and "directly" not in r.stderr
    assert out["pose_ur"]["z_m"] == pytest.approx(0.52, abs=1e-4)
    assert out["pose_ur"]["rx_rad"] == pytest.approx(3.1, abs=1e-4)
    r = run_cli("robot", "state", "--robot", "robot0", env={**env, "CELLCTL_URL": "http://127.0.0.1:9"})
    assert r.returncode == 2 and "cannot reach the service at http://127.0.0.1:9" in r.stderr
