"""The foundation commands as a user runs them: JSON on stdout, one-line errors, non-zero exits."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import pytest

from tests.conftest import CELLCTL, REPO
from tests.support.cli import run_cli as run


def test_config_default_prints_the_example() -> None:
    """The console script itself (the other tests call its ``main`` in-process)."""
    r = subprocess.run([CELLCTL, "config", "default"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0
    assert r.stdout == (REPO / "deploy" / "examples" / "virtual-cell.yaml").read_text()


def test_grab_and_robot_state(tmp_path: Path) -> None:
    out = tmp_path / "f.png"
    r = run("grab", "--camera", "cam0", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["width"] == 1280
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (960, 1280)
    r = run("robot", "state", "--local", "--robot", "robot0")  # the device, asked for by name (issue 36)
    assert r.returncode == 0
    s = json.loads(r.stdout)
    assert len(s["T_base_tool"]) == 4 and set(s["pose_ur"]) == {"x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"}


@pytest.mark.parametrize(
    ("text", "args", "message"),
    [
        ("cameras: {cam0: {kind: warp}}", ("grab", "--config", "{cfg}", "--camera", "cam0", "--out", "x.png"),
         "cameras.cam0.kind: unknown camera kind 'warp'"),
        ("cameras: [1, 2", ("robot", "state", "--config", "{cfg}", "--robot", "robot0"), "not valid YAML"),
        ("http: {port: -3}", ("sim", "truth", "--config", "{cfg}"), "http.port"),
    ],
)
def test_bad_config_is_a_one_line_error(tmp_path: Path, text: str, args: tuple[str, ...], message: str) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(text)
    r = run(*(a.replace("{cfg}", str(cfg)) for a in args), cwd=tmp_path)
    assert r.returncode != 0
    assert r.stderr.strip().count("\n") == 0, r.stderr
    assert message in r.stderr
    assert r.stdout == ""
    assert not (tmp_path / "x.png").exists()


def test_unknown_camera_and_robot(tmp_path: Path) -> None:
    r = run("grab", "--camera", "nope", "--out", str(tmp_path / "x.png"))
    assert r.returncode == 2 and "no camera 'nope'" in r.stderr
    r = run("robot", "state", "--local", "--robot", "nope")
    assert r.returncode == 2 and "no robot 'nope'" in r.stderr


def test_sim_truth_has_the_ground_truth() -> None:
    r = run("sim", "truth")
    assert r.returncode == 0
    t = json.loads(r.stdout)
    assert {"camera", "T_tool_cam", "T_base_cam", "targets", "parts"} <= set(t)
    assert t["targets"]["plate"]["target"]["type"] == "circle_plate"


def test_serve_on_a_taken_port_is_a_one_line_error(tmp_path: Path) -> None:
    import os
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = subprocess.run([CELLCTL, "serve", "--port", str(port)], capture_output=True, text=True, timeout=60,
                           env={**os.environ, "CELLCTL_DATA_DIR": str(tmp_path)})
    assert r.returncode == 2
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("cellctl: error: cannot listen for HTTP on 127.0.0.1:") and "Traceback" not in r.stderr
