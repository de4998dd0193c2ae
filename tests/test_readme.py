"""The README is tested: its set-up commands are CI's, and every tour command runs as shown."""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path

import httpx

from tests.conftest import REPO, free_port

README = (REPO / "README.md").read_text()
BLOCKS = re.findall(r"```bash\n(.*?)```", README, flags=re.S)


def test_readme_opens_with_the_two_commands() -> None:
    assert BLOCKS[0].strip() == "bash deploy/setup.sh && .venv/bin/cellctl serve"
    test_command = BLOCKS[1].strip()
    assert test_command.startswith("bash deploy/setup.sh && ")
    ci = (REPO / ".ci" / "run").read_text()
    assert test_command in ci.splitlines()


def tour_script(port: int) -> str:
    """The README's tour blocks, pointed at ``port`` instead of the documented 8080."""
    tour = "\n".join(BLOCKS[2:])
    assert "127.0.0.1:8080" in tour  # the README shows the default address; the test moves it
    script = tour.replace("127.0.0.1:8080", f"127.0.0.1:{port}")
    assert "8080" not in script, "a tour command names port 8080 in a form this test cannot move"
    return "set -euo pipefail\n" + script


def test_the_tour_runs_as_written(tmp_path: Path) -> None:
    """Start the service as the README's first command does (on a free port of its own, with its own
    HOME and so its own data dir), then run every tour block against that service, never against
    whatever else may listen on 8080."""
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
        r = subprocess.run(["bash", "-c", tour_script(port)], cwd=tmp_path, env={**env, "CELLCTL_URL": base},
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, f"stdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-3000:]}"
    finally:
        os.killpg(server.pid, 15)
        server.wait(timeout=30)
    # What the tour promised is there.
    assert (tmp_path / "frame.png").stat().st_size > 10000
    assert json.loads((tmp_path / "intrinsics.json").read_text())["state"] == "succeeded"
    assert json.loads((tmp_path / "handeye.json").read_text())["state"] == "succeeded"
    picks = json.loads((tmp_path / "picks.json").read_text())["picks"]
    assert picks and picks[0]["part"] == "bracket" and picks[0]["reachable"]
    truth = json.loads((tmp_path / "truth.json").read_text())
    bracket = next(p for p in truth["parts"] if p["name"] == "bracket")
    pose = picks[0]["pick_pose"]
    assert abs(pose["x_mm"] - bracket["x_mm"]) < 1.0 and abs(pose["y_mm"] - bracket["y_mm"]) < 1.0
    assert (tmp_path / "recording" / "manifest.json").exists()
    assert "sha256" in (tmp_path / "cell.yaml").read_text()
