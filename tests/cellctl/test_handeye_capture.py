"""The first calibration a user makes, through the service: both capture routines with their
defaults on the built-in virtual cell end with their verdicts ok and activate without force.

The cell is the built-in one with instantaneous robot moves (the robot's ``motion_time_scale``
setting), so the test spends its time on the stations, not on travel.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from cellctl.config import default_config_text
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.support.served import run_job


@pytest.fixture(scope="module")
def config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    data = yaml.safe_load(default_config_text())
    data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.0
    path = tmp_path_factory.mktemp("he-capture-config") / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, config: Path) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("he-capture"), config)
    try:
        yield s
    finally:
        stop_served(s)


@pytest.fixture(scope="module")
def first_calibration(served: Served) -> dict[str, Any]:
    """intrinsics-capture then handeye-capture, both with their defaults, each activated."""
    out: dict[str, Any] = {}
    with served.client(timeout_s=60) as http:
        for name in ("intrinsics-capture", "handeye-capture"):
            job = run_job(http, name, {}, timeout_s=900)
            assert job["state"] == "succeeded", job["error"]
            out[name] = job["result"]
            # No force: the guard refuses a calibration whose verdict is not ok.
            r = http.post(f"/calibrations/{job['result']['calibration_id']}/activate")
            out[name + " activation"] = r.status_code, r.text
            if name == "handeye-capture":
                out["events"] = job["events"]
    return out


@pytest.fixture(scope="module")
def truth(config: Path) -> dict[str, Any]:
    out = run_cellctl("sim", "truth", "--config", str(config), check=True).stdout
    return dict(json.loads(out))


def test_defaults_end_with_the_handeye_verdict_ok(first_calibration: dict[str, Any]) -> None:
    assert first_calibration["intrinsics-capture"]["verdict"]["ok"] is True
    assert first_calibration["intrinsics-capture activation"][0] == 200
    res = first_calibration["handeye-capture"]
    assert res["verdict"]["ok"] is True, res["verdict"]
    assert res["complete"] is True and res["coverage"]["missing"] == [] and res["verdict"]["coverage_missing"] == []
    assert first_calibration["handeye-capture activation"][0] == 200, first_calibration["handeye-capture activation"]
    cov = res["coverage"]
    assert cov["axis_separation_deg"] >= 45 and cov["axis_spread_deg"] >= 15 and cov["distance_range"] >= 0.15
    assert 10 <= res["stations_used"] <= res["stations_tried"] <= 24
    assert res["returned_to_start"] is True


def test_the_planned_stations_recover_T_tool_cam(first_calibration: dict[str, Any], truth: dict[str, Any]) -> None:
    res = first_calibration["handeye-capture"]
    rot, trans = g.transform_error(np.array(res["T_tool_cam"]), np.array(truth["T_tool_cam"]))
    sig = res["uncertainty"]
    assert trans * 1e3 < max(4 * sig["trans_mm"], 0.2), (trans * 1e3, sig)
    assert math.degrees(rot) < max(4 * sig["rot_deg"], 0.05), (math.degrees(rot), sig)
    assert res["loo_prediction_rms_px"] < 0.5
    assert res["camera_covariance_used"] is True  # intrinsics-capture's covariance enters the uncertainty


def test_the_moves_were_checked_and_audited(served: Served, first_calibration: dict[str, Any]) -> None:
    res = first_calibration["handeye-capture"]
    with served.client() as http:
        audit = http.get("/audit", params={"action": "robot.move", "limit": 200}).json()
        limits = http.get("/robots/robot0/state").json()
    moves = [a for a in audit if a["detail"]["why"].startswith("handeye-capture")]
    # A move to every station but the start, and one back to the start.
    assert len(moves) == res["stations_tried"]
    for a in moves:
        T = g.ur_pose_to_transform(a["detail"]["pose_ur"])
        assert 0.1 <= T[0, 3] <= 0.8 and -0.4 <= T[1, 3] <= 0.4 and 0.002 <= T[2, 3] <= 0.8
        assert math.degrees(math.acos(-T[2, 2])) <= 60.0  # the tool cone
    assert limits["moving"] is False


def test_the_parameters_are_typed_and_listed(served: Served) -> None:
    with served.client() as http:
        listed = {r["name"]: r for r in http.get("/routines").json()}
        r = http.post("/routines/handeye-capture", json={"max_stations": 2})
        assert r.status_code == 422 and "max_stations" in r.json()["error"]["message"]
        r = http.post("/routines/handeye-capture", json={"distance_range": 0.9})
        assert r.status_code == 422 and "distance_range" in r.json()["error"]["message"]
    props = listed["handeye-capture"]["params_schema"]["properties"]
    assert props["max_stations"]["default"] == 24 and props["stations"]["default"] == 10
    assert "fraction" in props["distance_range"]["description"] and "degrees" in props["max_spin_deg"]["description"]
    out = run_cellctl("job", "run", "--help", timeout=60).stdout
    assert "max_stations (integer, [4..80]; default 24)" in out and "distance_range" in out


def test_progress_names_each_station_and_what_is_missing(served: Served, first_calibration: dict[str, Any]) -> None:
    assert first_calibration["events"] > 3
    with served.client() as http:
        jobs = [j for j in http.get("/jobs").json() if j["name"] == "handeye-capture"]
        assert jobs and jobs[0]["message"] == "done"
        with http.stream("GET", f"/jobs/{jobs[0]['id']}/events") as stream:
            lines = [json.loads(line[6:]) for line in stream.iter_lines() if line.startswith("data: ")]
    stations = [e for e in lines if str(e.get("message", "")).startswith("station ")]
    assert stations and all("(" in e["message"] for e in stations[1:])
    assert any("coverage_missing" in e for e in stations)

