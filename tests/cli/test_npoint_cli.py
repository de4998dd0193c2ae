"""``cellctl calib npoint`` end to end, and its bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.io import write_pairs_csv
from calibration.synthetic import simulate_npoint
from cellctl.cli import main
from tests.support.cli import run_cli, run_process

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 960], [0, 1900.0, 600], [0, 0, 1]]),
                  np.array([-0.1, 0.02, 0.0, 0.0, 0.0]))


def test_npoint_tilted_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    uv, xy, truth = simulate_npoint(np.random.default_rng(0), CAM, tilt_deg=1.5)
    write_pairs_csv(tmp_path / "pairs.csv", uv, xy)
    (tmp_path / "cam.json").write_text(json.dumps(CAM.to_dict()))
    out = tmp_path / "np.json"
    assert main(["calib", "npoint", "--pairs", str(tmp_path / "pairs.csv"), "--camera", str(tmp_path / "cam.json"),
                 "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert json.loads(capsys.readouterr().out) == res
    assert res["model"] == "homography"
    assert set(res["loo_rms_mm"]) == {"similarity", "affine", "homography"}
    assert np.array(res["H"]).shape == (3, 3)
    assert set(res["affine"]) == {"sx", "sy", "phi_deg", "theta_deg", "tx_mm", "ty_mm"}
    assert res["rms_mm"] < 0.1 and res["field_sigma_mm"]["max"] < 0.1
    assert main(["calib", "npoint", "--pairs", str(tmp_path / "pairs.csv"), "--model", "affine"]) == 0
    assert json.loads(capsys.readouterr().out)["model"] == "affine"


def test_npoint_bad_input(tmp_path: Path) -> None:
    p = tmp_path / "pairs.csv"
    p.write_text("u_px,v_px,x_mm,y_mm\n100,100,0,0\n200,200,10,-10\n300,300,20,-20\n400,400,30,-30\n")
    r = run_process("calib", "npoint", "--pairs", str(p))  # the entry point once
    assert r.returncode == 2 and "collinear" in r.stderr and "Traceback" not in r.stderr
    p.write_text("u,v,x,y\n1,2,3,4\n")
    r = run_cli("calib", "npoint", "--pairs", str(p))
    assert r.returncode == 2 and "header must be u_px,v_px,x_mm,y_mm" in r.stderr
    r = run_cli("calib", "npoint", "--pairs", str(tmp_path / "none.csv"))
    assert r.returncode == 2 and "cannot read" in r.stderr
