"""jog-to-mark's tool-centre step end to end on ``cellctl serve`` with a fixed camera.

The scene (``drivers/sim/scenes/virtual-cell-fixed-camera.yaml``) has a camera fixed above a
level circle plate and a bright disk on the gripper, 28 / -12 mm off the flange axis and 150 mm
down the tool. The test plays the operator: it jogs the tool so that the disk sits on each mark
(over the API, from the scene's truth) and presses record. The routine then turns the tool at one
mark, sees the disk at each angle and fits the tool centre, which must match the scene's truth
within the reported uncertainty. A Stop during the turn ends the job stopped, with nothing stored.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.targets import target_from_dict
from cellctl.cli import main
from tests.conftest import REPO, Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.support.wait import wait_until

SCENE = REPO / "drivers" / "sim" / "scenes" / "virtual-cell-fixed-camera.yaml"
R_DOWN = g.rotvec_to_matrix([np.pi, 0.0, 0.0])


def _config(tmp: Path) -> Path:
    cfg = yaml.safe_load((REPO / "deploy" / "examples" / "virtual-cell.yaml").read_text())
    cfg["cameras"]["cam0"]["settings"]["scene"] = str(SCENE)
    cfg["robots"]["robot0"]["settings"]["scene"] = str(SCENE)
    cfg["calibration"]["setup"] = "eye-to-hand"
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.fixture(scope="module")
def tokens(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp = tmp_path_factory.mktemp("tcp")
    cfg = _config(tmp)
    out: dict[str, Any] = {"tmp": tmp, "config": cfg}
    for role in ("operator", "engineer"):
        f = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-1", "--role", role,
                     "--out", str(f)]) == 0
        out[role] = json.loads(f.read_text())["token"]
    return out


@pytest.fixture(scope="module")
def served(tokens: dict[str, Any]) -> Iterator[Served]:
    s = start_served(tokens["tmp"], config=tokens["config"], token=tokens["engineer"])
    try:
        yield s
    finally:
        stop_served(s)


@pytest.fixture(scope="module")
def truth(served: Served) -> dict[str, Any]:
    out = run_cellctl("sim", "truth", "--config", str(served.data_dir.parent / "cell.yaml"), check=True).stdout
    return dict(json.loads(out))


def _flange_for_mark(truth: dict[str, Any], mark_id: int) -> dict[str, float]:
    """The tool pose (pointing down) that puts the disk on mark ``mark_id``."""
    plate = truth["targets"]["plate"]
    pts = target_from_dict(plate["target"]).points()
    p = g.transform_points(np.array(plate["T_base_target"]), pts.xyz_m[list(pts.ids).index(mark_id)])[0]
    f = p - R_DOWN @ (np.array(truth["tool_feature"]["offset_mm"]) * 1e-3)
    return {"x_m": f[0], "y_m": f[1], "z_m": f[2], "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}


def _wait_input(http: httpx.Client, job_id: str, step: int) -> dict[str, Any]:
    """The routine's request for mark ``step`` (the previous request may still show for a moment)."""
    deadline = time.monotonic() + 60
    while ((job := http.get(f"/jobs/{job_id}").json())["waiting_for"] or {}).get("step") != step:
        assert job["state"] == "running", job["error"]
        assert time.monotonic() < deadline
        time.sleep(0.1)
    return dict(job["waiting_for"])


def _wait_end(http: httpx.Client, job_id: str, timeout_s: float = 120) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while (job := http.get(f"/jobs/{job_id}").json())["state"] == "running":
        assert time.monotonic() < deadline
        time.sleep(0.2)
    return dict(job)


def _record_marks(http: httpx.Client, truth: dict[str, Any], job_id: str, n: int) -> None:
    for step in range(1, n + 1):
        mark = _wait_input(http, job_id, step)
        pose = _flange_for_mark(truth, mark["mark_id"])
        assert http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.25}).status_code == 200
        assert http.post(f"/jobs/{job_id}/record").status_code == 200


def _home(http: httpx.Client) -> None:
    home = {"x_m": 0.40, "y_m": -0.30, "z_m": 0.30, "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}
    assert http.post("/robots/robot0/move", json={"pose_ur": home, "speed_m_s": 0.25}).status_code == 200


def test_the_turn_recovers_the_tool_centre(served: Served, truth: dict[str, Any]) -> None:
    with served.client(timeout_s=60) as http:
        _home(http)
        r = http.post("/routines/jog-to-mark", json={"marks": 9, "tool_centre": True})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        _record_marks(http, truth, job_id, 9)
        job = _wait_end(http, job_id)
        assert job["state"] == "succeeded", job["error"]
        res = job["result"]
        assert res["verdict"]["ok"] is True, res["verdict"]
        tc = res["tool_centre"]
        assert len(tc["rotations"]) == 7 and tc["mark_step"] == 5  # the centre of the 3x3 marks
        true_xy_mm = np.array(truth["tool_feature"]["offset_mm"][:2])
        got_xy_mm = np.array(tc["offset_tool_m"][:2]) * 1e3
        # offset_mm is base-aligned at the mark's orientation (tool pointing down: y flips)
        assert np.allclose(R_DOWN[:2, :2] @ got_xy_mm, tc["offset_mm"], atol=0.01)  # reported pose: 0.005 deg noise
        sigma = np.array(tc["uncertainty"]["offset_axes_mm"])
        err = np.abs(got_xy_mm - true_xy_mm)
        assert np.all(err <= np.maximum(3 * sigma, 0.01)), (err, sigma)
        assert np.all(err < 0.1) and np.all(sigma < 0.1), (err, sigma)
        assert tc["rms_mm"] < 0.05
        # The arc's centre is the flange axis at the mark: close to the pose the robot reported there.
        assert tc["positions"][0]["arc_deg"] == pytest.approx(180.0, abs=0.1)
        # Stored with the N-point calibration, verdict and all.
        stored = http.get(f"/calibrations/{res['calibration_id']}").json()
        assert stored["result"]["tool_centre"]["offset_mm"] == tc["offset_mm"]
        assert stored["result"]["verdict"]["ok"] is True
        # The turn left the robot free again: the operator can jog.
        _home(http)


def test_the_turn_needs_the_engineer_and_valid_angles(served: Served, tokens: dict[str, Any]) -> None:
    with served.client(token=tokens["operator"]) as http:
        r = http.post("/routines/jog-to-mark", json={"marks": 4, "tool_centre": True})
        assert r.status_code == 403 and "engineer" in r.json()["error"]["message"], r.text
    with served.client() as http:
        for angles, why in (([0, 10, 20], "span 20 deg"), ([0, 90], "at least 3"), ([0, 45, 200], "-180..180")):
            r = http.post("/routines/jog-to-mark", json={"tool_centre": True, "tcp_angles_deg": angles})
            assert r.status_code == 422 and why in r.json()["error"]["message"], r.text
        r = http.post("/routines/jog-to-mark", json={"marks": 4, "tool_centre": True, "tcp_mark": 9})
        assert r.status_code == 422 and "only 4 marks will be recorded" in r.json()["error"]["message"], r.text


def test_a_stop_during_the_turn_ends_the_job_stopped(served: Served, truth: dict[str, Any]) -> None:
    with served.client(timeout_s=60) as http:
        _home(http)
        before = len(http.get("/calibrations").json())
        r = http.post("/routines/jog-to-mark", json={"marks": 4, "tool_centre": True, "speed_m_s": 0.05})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        _record_marks(http, truth, job_id, 4)
        deadline = time.monotonic() + 60
        while "turning the tool" not in (job := http.get(f"/jobs/{job_id}").json())["message"]:
            assert job["state"] == "running", job["error"]
            assert time.monotonic() < deadline
            time.sleep(0.05)
        # The routine owns the robot now, turning the tool: a jog is refused.
        wait_until(lambda: http.get("/robots/robot0/state").json()["moving"], 30.0, "the turn under way")
        pose = _flange_for_mark(truth, 0)
        assert http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.1}).status_code == 409
        assert http.post("/robots/robot0/stop").status_code == 200
        job = _wait_end(http, job_id)
        assert job["state"] == "stopped", job
        assert len(http.get("/calibrations").json()) == before
        assert http.post("/robots/robot0/resume").status_code == 200
        _home(http)
