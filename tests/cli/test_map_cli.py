"""``cellctl map`` with np.json and he.json, and its bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, transform_points, transform_to_ur_pose
from calibration.handeye import RobotNoise, calibrate_handeye
from calibration.npoint import fit_npoint
from calibration.synthetic import simulate_handeye, simulate_npoint
from calibration.targets import Chessboard
from cellctl.cli import main
from tests.support.cli import run_cli, run_process

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))


def test_map_npoint(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    uv, xy, truth = simulate_npoint(np.random.default_rng(1), CAM, tilt_deg=1.5)
    (tmp_path / "np.json").write_text(json.dumps(fit_npoint(uv, xy).to_json()))
    assert main(["map", "--calib", str(tmp_path / "np.json"), "800", "640"]) == 0
    out = json.loads(capsys.readouterr().out)
    t = truth(np.array([[800.0, 640.0]]))[0]
    assert np.hypot(out["x_mm"] - t[0], out["y_mm"] - t[1]) < 3 * out["sigma"]["total_mm"]
    assert out["u_px"] == 800.0 and out["sigma"]["total_mm"] > 0


def test_map_eye_in_hand(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(5), camera=CAM, target=Chessboard(8, 6, 30.0),
                           robot_noise=RobotNoise(0.05, 0.01))
    res = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, Chessboard(8, 6, 30.0),
                            leave_one_out=False)
    he = tmp_path / "he.json"
    he.write_text(json.dumps(res.to_json()))
    (tmp_path / "cam.json").write_text(json.dumps(CAM.to_dict()))
    G = sim.G_true[3]
    T_base_cam = G @ sim.X_true
    P = T_base_cam[:3, 3] + 0.4 * T_base_cam[:3, 2]
    uv = CAM.project(transform_points(invert(T_base_cam), P[None]))[0]
    pose = ",".join(repr(float(v)) for v in transform_to_ur_pose(G))
    assert main(["map", "--calib", str(he), "--camera", str(tmp_path / "cam.json"), "--plane-z-mm",
                 repr(float(P[2] * 1e3)), "--robot-pose", pose, "--pixel-sigma-px", "0",
                 repr(float(uv[0])), repr(float(uv[1]))]) == 0
    out = json.loads(capsys.readouterr().out)
    err = np.array([out["x_mm"], out["y_mm"], out["z_mm"]]) - P * 1e3
    assert np.linalg.norm(err) < 3 * out["sigma"]["total_mm"] < 3.0
    # missing robot pose: one clear line, exit 2
    r = run_process("map", "--calib", str(he), "--plane-z-mm", "0", "100", "100")  # the entry point once
    assert r.returncode == 2 and "robot pose at capture" in r.stderr and "Traceback" not in r.stderr
    assert "give --robot-pose x,y,z,rx,ry,rz" in r.stderr  # the CLI words the library's hint with its flag
    r = run_cli("map", "--calib", str(he), "--plane-z-mm", "0", "--robot-pose", "1,2,3",
                        "100", "100")
    assert r.returncode == 2 and "six numbers" in r.stderr


def test_map_bad_calibration_file(tmp_path: Path) -> None:
    bad = tmp_path / "x.json"
    bad.write_text("{not json")
    r = run_cli("map", "--calib", str(bad), "1", "2")
    assert r.returncode == 2 and "not valid JSON" in r.stderr
    bad.write_text(json.dumps({"hello": 1}))
    r = run_cli("map", "--calib", str(bad), "1", "2")
    assert r.returncode == 2 and "np.json" in r.stderr
