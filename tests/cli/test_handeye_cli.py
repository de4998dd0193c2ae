"""``cellctl calib handeye`` end to end on rendered images + poses.csv, and its bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import transform_to_ur_pose
from calibration.handeye import RobotNoise, transform_error_deg_mm
from calibration.io import write_poses_csv
from calibration.synthetic import SimulatedHandEye, simulate_handeye
from calibration.targets import Chessboard
from cellctl.cli import main
from drivers.sim.imaging import Imaging, PlanarObject, render

CELLCTL = str(Path(sys.executable).with_name("cellctl"))
CAM = CameraModel("opencv5", 640, 480, np.array([[720.0, 0, 322], [0, 720.0, 238], [0, 0, 1]]),
                  np.array([-0.05, 0.02, 0.0, 0.0, 0.0]))
BOARD = Chessboard(7, 5, 30.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SimulatedHandEye]:
    d = tmp_path_factory.mktemp("he")
    sim = simulate_handeye("eye-in-hand", 8, np.random.default_rng(2), camera=CAM, target=BOARD,
                           robot_noise=RobotNoise(0.05, 0.01), distance_m=(0.45, 0.6))
    names = []
    for k, C in enumerate(sim.C_true):
        img = render(CAM, [PlanarObject(C, BOARD.reflectance)], Imaging(noise_sigma=2.0, blur_sigma_px=0.5),
                     np.random.default_rng(k))
        names.append(f"station_{k:02d}.png")
        cv2.imwrite(str(d / names[-1]), img)
    write_poses_csv(d / "poses.csv", names, np.array([transform_to_ur_pose(g) for g in sim.G_recorded]))
    (d / "board.yaml").write_text("type: chessboard\ncols: 7\nrows: 5\nsquare_mm: 30.0\n")
    (d / "cam.json").write_text(json.dumps(CAM.to_dict()))
    return d, sim


def test_handeye_from_images(dataset: tuple[Path, SimulatedHandEye], tmp_path: Path,
                             capsys: pytest.CaptureFixture[str]) -> None:
    d, sim = dataset
    out = tmp_path / "he.json"
    code = main(["calib", "handeye", "--setup", "eye-in-hand", "--camera", str(d / "cam.json"),
                 "--target", str(d / "board.yaml"), "--dataset", str(d), "--out", str(out)])
    assert code == 0
    he = json.loads(out.read_text())
    assert json.loads(capsys.readouterr().out) == he
    rot_deg, trans_mm = transform_error_deg_mm(np.array(he["T_tool_cam"]), sim.X_true)
    assert rot_deg < 3 * he["uncertainty"]["rot_deg"] and trans_mm < 3 * he["uncertainty"]["trans_mm"]
    assert he["setup"] == "eye-in-hand" and "T_base_target" in he
    assert he["rms_px"] < 0.3 and len(he["poses"]) == 8
    assert {"mean", "rms", "max"} <= set(he["rot_deg"]) and {"mean", "rms", "max"} <= set(he["trans_mm"])
    assert he["leave_one_out"]["position_mm"]["rms"] < 2.0
    # the detections path gives the same answer without re-detecting
    dets = tmp_path / "dets.json"
    assert main(["detect", "--target", str(d / "board.yaml"), *sorted(str(p) for p in d.glob("*.png"))]) == 0
    det_list = json.loads(capsys.readouterr().out)
    for item in det_list:
        item["image"] = Path(item["image"]).name
    dets.write_text(json.dumps(det_list))
    assert main(["calib", "handeye", "--setup", "eye-in-hand", "--camera", str(d / "cam.json"), "--target",
                 str(d / "board.yaml"), "--dataset", str(d), "--detections", str(dets), "--no-loo"]) == 0
    he2 = json.loads(capsys.readouterr().out)
    assert np.allclose(he2["T_tool_cam"], he["T_tool_cam"], atol=1e-6)


def test_poses_in_millimetres_named(dataset: tuple[Path, SimulatedHandEye], tmp_path: Path) -> None:
    d, sim = dataset
    bad = tmp_path / "mm"
    bad.mkdir()
    for p in d.glob("*.png"):
        (bad / p.name).symlink_to(p)
    raw = np.array([transform_to_ur_pose(g) for g in sim.G_recorded])
    raw[:, :3] *= 1000.0
    write_poses_csv(bad / "poses.csv", [f"station_{k:02d}.png" for k in range(8)], raw)
    r = subprocess.run([CELLCTL, "calib", "handeye", "--setup", "eye-in-hand", "--camera", str(d / "cam.json"),
                        "--target", str(d / "board.yaml"), "--dataset", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "millimetres" in r.stderr and "divide x, y, z by 1000" in r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("cellctl: error:")]
    assert "Traceback" not in r.stderr and len(errors) == 1 and "millimetres" in errors[0]


def test_bad_dataset(dataset: tuple[Path, SimulatedHandEye], tmp_path: Path, capsys: pytest.CaptureFixture[str]
                     ) -> None:
    d, _ = dataset
    args = ["calib", "handeye", "--setup", "eye-to-hand", "--camera", str(d / "cam.json"), "--target",
            str(d / "board.yaml"), "--dataset"]
    assert main([*args, str(tmp_path / "nope")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err
    assert main([*args, str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "poses.csv" in err and "cannot read" in err
    (tmp_path / "poses.csv").write_text("image,x,y,z,rx,ry,rz\nmissing.png,0.4,0,0.3,0,3.1,0\n")
    assert main([*args, str(tmp_path)]) == 2
    assert "not there" in capsys.readouterr().err


def test_camera_covariance_enters_the_uncertainty(dataset: tuple[Path, SimulatedHandEye], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """cam.json's parameters.covariance (as calib intrinsics writes it) is propagated into he.json's
    uncertainty; a malformed one is named."""
    d, sim = dataset
    dets = tmp_path / "dets.json"
    items = []
    for k, det in enumerate(sim.detections):
        item = det.to_json()
        item["image"] = f"station_{k:02d}.png"
        items.append(item)
    dets.write_text(json.dumps(items))
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    sd = np.array([4.0, 4.0, 3.0, 3.0, 0.005, 0.01, 1e-4, 1e-4, 0.0])
    cam = CAM.to_dict()
    cam_cov = tmp_path / "cam_cov.json"
    cam_cov.write_text(json.dumps({**cam, "parameters": {"names": names, "covariance": np.diag(sd**2).tolist()}}))
    base = ["calib", "handeye", "--setup", "eye-in-hand", "--target", str(d / "board.yaml"), "--dataset", str(d),
            "--detections", str(dets), "--no-loo", "--camera"]
    assert main([*base, str(d / "cam.json")]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert main([*base, str(cam_cov)]) == 0
    withcov = json.loads(capsys.readouterr().out)
    assert plain["uncertainty"]["camera"] == "none" and withcov["uncertainty"]["camera"] == "propagated"
    assert np.allclose(withcov["T_tool_cam"], plain["T_tool_cam"], atol=1e-9)  # the estimate is unchanged
    # a 4 px focal-length and 3 px centre uncertainty at 720 px moves a camera 0.5 m away by millimetres
    assert withcov["uncertainty"]["trans_mm"] > 3 * plain["uncertainty"]["trans_mm"]
    assert withcov["uncertainty"]["rot_deg"] > plain["uncertainty"]["rot_deg"]
    bad = tmp_path / "cam_bad.json"
    bad.write_text(json.dumps({**cam, "parameters": {"names": names, "covariance": [[1.0, 0.0], [0.0, 1.0]]}}))
    assert main([*base, str(bad)]) == 2
    err = capsys.readouterr().err
    assert "parameters.covariance" in err and "square matrix" in err
