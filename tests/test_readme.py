"""The README is tested: its set-up commands are CI's, and every tour command runs as shown."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from calibration import geometry as g
from tests.conftest import REPO, free_port

README = (REPO / "README.md").read_text()
BLOCKS = re.findall(r"```bash\n(.*?)```", README, flags=re.S)
_PRODUCTION = README[README.index("### A production run"):]
_PRODUCTION = _PRODUCTION[:_PRODUCTION.index("\n#", 1)]
PRODUCTION_BLOCKS = re.findall(r"```bash\n(.*?)```", _PRODUCTION, flags=re.S)
"""The tour's production run: its own cell and service (``test_the_production_tour_runs_as_written``)."""
_CONVEYOR = README[README.index("### A conveyor run"):]
_CONVEYOR = _CONVEYOR[:_CONVEYOR.index("\n#", 1)]
CONVEYOR_BLOCKS = re.findall(r"```bash\n(.*?)```", _CONVEYOR, flags=re.S)
"""The tour's conveyor run: its own cell and service (``test_the_conveyor_tour_runs_as_written``)."""
TOUR_BLOCKS = [b for b in BLOCKS[2:] if b not in PRODUCTION_BLOCKS and b not in CONVEYOR_BLOCKS]


def test_readme_opens_with_the_two_commands() -> None:
    assert BLOCKS[0].strip() == "bash deploy/setup.sh && .venv/bin/cellctl serve"
    test_command = BLOCKS[1].strip()
    assert test_command.startswith("bash deploy/setup.sh && ")
    ci = (REPO / ".ci" / "run").read_text()
    assert test_command in ci.splitlines()


def tour_script(port: int) -> str:
    """The README's tour blocks (but the production run's), pointed at ``port`` instead of the documented 8080."""
    tour = "\n".join(TOUR_BLOCKS)
    assert "127.0.0.1:8080" in tour  # the README shows the default address; the test moves it
    script = tour.replace("127.0.0.1:8080", f"127.0.0.1:{port}")
    assert "8080" not in script, "a tour command names port 8080 in a form this test cannot move"
    return "set -euo pipefail\n" + script


def _check_the_tour_results(cwd: Path) -> tuple[int, int]:
    """What the tour promised is there; answers the two calibration ids it stored."""
    assert (cwd / "frame.png").stat().st_size > 10000
    intrinsics = json.loads((cwd / "intrinsics.json").read_text())
    handeye = json.loads((cwd / "handeye.json").read_text())
    assert intrinsics["state"] == "succeeded" and handeye["state"] == "succeeded"
    picks = json.loads((cwd / "picks.json").read_text())["picks"]
    assert picks and picks[0]["part"] == "bracket" and picks[0]["reachable"]
    truth = json.loads((cwd / "truth.json").read_text())
    bracket = next(p for p in truth["parts"] if p["name"] == "bracket")
    pose = picks[0]["pick_pose"]
    assert abs(pose["x_mm"] - bracket["x_mm"]) < 1.0 and abs(pose["y_mm"] - bracket["y_mm"]) < 1.0
    # `record` never writes into a folder that holds data: the tour names a new one each time.
    assert [p for p in cwd.glob("recording-*") if (p / "manifest.json").exists()]
    assert "sha256" in (cwd / "cell.yaml").read_text()
    return int(intrinsics["result"]["calibration_id"]), int(handeye["result"]["calibration_id"])


@pytest.mark.timeout(1800)  # two whole tours with a real-time robot: ~2 x 4 min on an idle machine
def test_the_tour_runs_as_written_twice_on_one_store(tmp_path: Path) -> None:
    """Start the service as the README's first command does (on a free port of its own, with its own
    HOME and so its own data dir), then run every tour block against that service, never against
    whatever else may listen on 8080 — and then run the whole tour again, unchanged, in the same
    folder against the same service and store (a user repeating it: the ids come from the answers,
    the files are overwritten, the robot starts where the first tour left it)."""
    (tmp_path / ".venv").symlink_to(REPO / ".venv")
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XDG_", "CELLCTL_"))}
    env["HOME"] = str(tmp_path)
    serve_cmd = BLOCKS[0].split("&&", 1)[1].strip() + f" --port {port}"
    log = (tmp_path / "serve.log").open("wb")
    server = subprocess.Popen(serve_cmd, shell=True, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    token_file = tmp_path / ".local" / "share" / "cellctl" / "virtual-cell.session-token"
    ids: list[tuple[int, int]] = []
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if token_file.is_file() and httpx.get(base + "/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert server.poll() is None, (tmp_path / "serve.log").read_text()
            assert time.monotonic() < deadline, f"the service did not come up on {base}"
            time.sleep(0.3)
        # The service that answers is ours: it knows the session token it wrote into our HOME.
        token = token_file.read_text().strip()
        me = httpx.get(base + "/robots/robot0/state", headers={"Authorization": f"Bearer {token}"}, timeout=10)
        assert me.status_code == 200, me.text
        for run in (1, 2):
            r = subprocess.run(["bash", "-c", tour_script(port)], cwd=tmp_path, env={**env, "CELLCTL_URL": base},
                               capture_output=True, text=True, timeout=900)
            assert r.returncode == 0, f"run {run}\nstdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-3000:]}"
            ids.append(_check_the_tour_results(tmp_path))
        active = httpx.get(base + "/calibrations", headers={"Authorization": f"Bearer {token}"}, timeout=10)
        assert active.status_code == 200, active.text
    finally:
        os.killpg(server.pid, 15)
        server.wait(timeout=30)
    # The second tour stored new versions (it read its ids from the answers, not 1 and 2) and
    # activated them.
    (cam1, he1), (cam2, he2) = ids
    assert len([p for p in tmp_path.glob("recording-*") if (p / "manifest.json").exists()]) == 2
    assert len({cam1, he1, cam2, he2}) == 4 and cam2 > cam1 and he2 > he1
    active_ids = {int(c["id"]) for c in active.json() if c["active"]}
    assert {cam2, he2} <= active_ids and not {cam1, he1} & active_ids


def _serve(cmd: str, cwd: Path, env: dict[str, str], base: str, token_file: Path) -> subprocess.Popen[bytes]:
    """Start ``cmd`` (a README serve line) and wait until it answers on ``base`` and wrote its token."""
    log = (cwd / "serve.log").open("wb")
    server = subprocess.Popen(cmd, shell=True, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)
    deadline = time.monotonic() + 60
    while True:
        try:
            if token_file.is_file() and httpx.get(base + "/health", timeout=2).status_code == 200:
                return server
        except httpx.HTTPError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            os.killpg(server.pid, 15)
            raise AssertionError(f"the service did not come up on {base}:\n" + (cwd / "serve.log").read_text())
        time.sleep(0.3)


def _run_served_section(tmp_path: Path, blocks: list[str], config_name: str, port: str, cell_id: str,
                        timeout_s: float) -> None:
    """A README section that serves its own cell: its first block's config and serve lines (the serve on a
    free port of its own instead of the documented ``port``, with ``tmp_path`` as HOME), then every
    command of its other blocks as written against that service; the service is stopped after."""
    (tmp_path / ".venv").symlink_to(REPO / ".venv")
    config_line, serve_line = blocks[0].strip().splitlines()
    assert serve_line.startswith(f".venv/bin/cellctl serve --config {config_name}") and f"--port {port}" in serve_line
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XDG_", "CELLCTL_"))}
    env["HOME"] = str(tmp_path)
    subprocess.run(["bash", "-c", "set -euo pipefail\n" + config_line], cwd=tmp_path, env=env, check=True, timeout=60)
    free = free_port()
    base = f"http://127.0.0.1:{free}"
    token_file = tmp_path / ".local" / "share" / "cellctl" / f"{cell_id}.session-token"
    server = _serve(serve_line.replace(port, str(free)), tmp_path, env, base, token_file)
    try:
        script = "\n".join(blocks[1:]).replace(f"127.0.0.1:{port}", f"127.0.0.1:{free}")
        assert port not in script and "8080" not in script, f"a command names port {port} where it cannot be moved"
        r = subprocess.run(["bash", "-c", "set -euo pipefail\n" + script], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=timeout_s)
        assert r.returncode == 0, f"stdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-3000:]}"
    finally:
        os.killpg(server.pid, 15)
        server.wait(timeout=30)


def _slot_errors(truth: dict[str, Any]) -> list[tuple[int, float, float]]:
    """Each placed part's slot with its position (mm) and angle (deg) error against that slot's pose."""
    grid = truth["place_grid"]
    T_origin = g.ur_pose_to_transform(grid["origin_ur"])
    slots = [T_origin @ g.make_transform(np.eye(3), [c * grid["pitch_mm"][0] * 1e-3, r * grid["pitch_mm"][1] * 1e-3,
                                                     0.0])
             for r in range(grid["rows"]) for c in range(grid["cols"])]
    out = []
    for part in truth["parts"]:
        if part["state"] == "placed":
            T = np.array(part["T_base_part"])
            k = min(range(len(slots)), key=lambda i: float(np.linalg.norm(slots[i][:3, 3] - T[:3, 3])))
            rot, trans = g.transform_error(T, slots[k])
            out.append((k, trans * 1e3, math.degrees(rot)))
    return sorted(out)


@pytest.mark.timeout(600)  # about a minute with the README's motion time scale 0.25
def test_the_production_tour_runs_as_written(tmp_path: Path) -> None:
    """The production run of the tour: its config line, its serve line (on a free port of its own, with
    its own HOME), then every command of the section as written; the production cell is calibrated by
    its own routines (both verdicts ok), and the run places three parts into the first three slots."""
    _run_served_section(tmp_path, PRODUCTION_BLOCKS, "production.yaml", "8081", "production-cell", timeout_s=500)
    assert "motion_time_scale: 0.25" in (tmp_path / "production.yaml").read_text()
    for name in ("p-intrinsics.json", "p-handeye.json"):
        job = json.loads((tmp_path / name).read_text())
        assert job["state"] == "succeeded" and job["verdict_ok"] is True, (name, job["result"])
    run = json.loads((tmp_path / "p-production.json").read_text())
    assert run["state"] == "complete" and run["ended_because"] == "count_reached", run
    assert run["counters"]["placed"] == 3 and run["next_slot"] == 3, run
    rows = list(csv.DictReader((tmp_path / "p-cycles.csv").read_text().splitlines()))
    assert [(row["result"], row["slot"]) for row in rows] == [("placed", "0"), ("placed", "1"), ("placed", "2")]
    errors = _slot_errors(json.loads((tmp_path / "p-truth.json").read_text()))
    assert [k for k, _, _ in errors] == [0, 1, 2], errors
    assert all(mm < 1.0 and deg < 1.0 for _, mm, deg in errors), errors


@pytest.mark.timeout(900)  # about four minutes at real time on an idle machine
def test_the_conveyor_tour_runs_as_written(tmp_path: Path) -> None:
    """The conveyor run of the tour: its config and serve lines (a free port, its own HOME), then every
    command of the section as written: the camera and hand-eye calibrated by their routines, the part
    taught with the belt still, the belt calibrated by ``conveyor-calibrate`` against the truth, and a
    run at 100 mm/s that meets three parts on the moving belt and places them into the first three
    slots within a millimetre and a degree, none missed."""
    _run_served_section(tmp_path, CONVEYOR_BLOCKS, "conveyor.yaml", "8082", "conveyor-cell", timeout_s=800)
    for name in ("c-intrinsics-capture.json", "c-handeye-capture.json", "c-belt.json"):
        job = json.loads((tmp_path / name).read_text())
        assert job["state"] == "succeeded" and job["verdict_ok"] is True, (name, job["result"])
    truth = json.loads((tmp_path / "c-truth.json").read_text())
    belt = json.loads((tmp_path / "c-belt.json").read_text())["result"]
    assert abs(belt["ticks_per_m"] - truth["conveyor"]["ticks_per_m"]) < max(4 * belt["sigma_ticks_per_m"], 5.0), belt
    run = json.loads((tmp_path / "c-production.json").read_text())
    assert run["state"] == "complete" and run["ended_because"] == "count_reached", run
    assert run["counters"]["placed"] == 3 and run["counters"].get("missed_window", 0) == 0, run
    rows = list(csv.DictReader((tmp_path / "c-cycles.csv").read_text().splitlines()))
    assert [(row["result"], row["slot"]) for row in rows if row["result"] == "placed"] == [
        ("placed", "0"), ("placed", "1"), ("placed", "2")], rows
    errors = _slot_errors(truth)
    assert [k for k, _, _ in errors] == [0, 1, 2], errors
    assert all(mm < 1.0 and deg < 1.0 for _, mm, deg in errors), errors
