"""The README is tested: its set-up commands are CI's, and every tour command runs as shown."""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path

import httpx

from tests.conftest import REPO

README = (REPO / "README.md").read_text()
BLOCKS = re.findall(r"```bash\n(.*?)```", README, flags=re.S)


def test_readme_opens_with_the_two_commands() -> None:
    assert BLOCKS[0].strip() == "bash deploy/setup.sh && .venv/bin/cellctl serve"
    test_command = BLOCKS[1].strip()
    assert test_command.startswith("bash deploy/setup.sh && ")
    ci = (REPO / ".ci" / "run").read_text()
    assert test_command in ci.splitlines()


def test_the_tour_runs_as_written(tmp_path: Path) -> None:
    """Start the service exactly as the README's first command does, then run every tour block."""
    (tmp_path / ".venv").symlink_to(REPO / ".venv")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XDG_", "CELLCTL_"))}
    env["HOME"] = str(tmp_path)
    serve_cmd = BLOCKS[0].split("&&", 1)[1].strip()
    log = (tmp_path / "serve.log").open("wb")
    server = subprocess.Popen(serve_cmd, shell=True, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get("http://127.0.0.1:8080/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert server.poll() is None, (tmp_path / "serve.log").read_text()
            assert time.monotonic() < deadline, "the service did not come up on 127.0.0.1:8080"
            time.sleep(0.3)
        script = "set -euo pipefail\n" + "\n".join(BLOCKS[2:])
        r = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=900)
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
