"""``cellctl pose``, ``cellctl measure`` and ``cellctl calib dlt`` end to end, and their bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, look_at, transform_error
from calibration.targets import Chessboard
from cellctl.cli import main
from drivers.sim.imaging import Imaging, PlanarObject, render

CAM = CameraModel("opencv5", 640, 480, np.array([[600.0, 0, 322], [0, 600, 238], [0, 0, 1]]),
                  np.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 20.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    d = tmp_path_factory.mktemp("pose")
    T = invert(look_at([0.02, 0.0, -0.45], [0.07, 0.05, 0.0], up=[0, -1, 0]))
    img = render(CAM, [PlanarObject(T, BOARD.reflectance)], Imaging(noise_sigma=1.0, blur_sigma_px=0.6),
                 np.random.default_rng(0))
    cv2.imwrite(str(d / "img.png"), img)
    (d / "board.yaml").write_text("type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 20.0\n")
    (d / "cam.json").write_text(json.dumps(CAM.to_dict()))
    return d, T


def test_pose_then_measure(scene: tuple[Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
                           ) -> None:
    d, T = scene
    pose = tmp_path / "pose.json"
    assert main(["pose", "--camera", str(d / "cam.json"), "--target", str(d / "board.yaml"), str(d / "img.png"),
                 "--out", str(pose)]) == 0
    res = json.loads(pose.read_text())
    rot, trans = transform_error(res["T_cam_target"], T)
    assert np.degrees(rot) < 0.2 and trans < 1e-3
    assert res["rms_px"] < 0.3 and res["uncertainty"]["trans_mm"] > 0
    # corner (row 2, col 3) of the board lies at (60, 40) mm
    uv = CAM.project((T[:3, :3] @ np.array([0.06, 0.04, 0.0]) + T[:3, 3])[None])[0]
    capsys.readouterr()
    assert main(["measure", "--camera", str(d / "cam.json"), "--plane", str(pose), str(uv[0]), str(uv[1])]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out[0]["x_mm"] == pytest.approx(60.0, abs=0.3) and out[0]["y_mm"] == pytest.approx(40.0, abs=0.3)


def test_measure_bad_input(scene: tuple[Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
                           ) -> None:
    d, _ = scene
    assert main(["measure", "--camera", str(d / "cam.json"), "--plane", str(d / "cam.json"), "1", "2"]) == 2
    assert "lacks 'T_cam_target'" in capsys.readouterr().err
    pose = tmp_path / "p.json"
    pose.write_text(json.dumps({"T_cam_target": np.eye(4).tolist()}))
    assert main(["measure", "--camera", str(d / "cam.json"), "--plane", str(pose), "1", "2", "3"]) == 2
    assert "pairs" in capsys.readouterr().err
    assert main(["measure", "--camera", str(d / "board.yaml"), "--plane", str(pose), "1", "2"]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def test_pose_bad_input(scene: tuple[Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d, _ = scene
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    assert main(["pose", "--camera", str(d / "cam.json"), "--target", str(d / "board.yaml"), str(blank)]) == 2
    assert "target not found" in capsys.readouterr().err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(d / "img.png")), (320, 240)))
    main(["pose", "--camera", str(d / "cam.json"), "--target", str(d / "board.yaml"), str(small)])
    err = capsys.readouterr().err
    assert "cellctl: error:" in err


def _points3d(tmp_path: Path, coplanar: bool = False) -> tuple[Path, Path]:
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-0.1, 0.1, 24), rng.uniform(-0.08, 0.08, 24),
                         np.zeros(24) if coplanar else rng.uniform(0, 0.08, 24)])
    T = invert(look_at([0.1, -0.15, -0.45], [0.0, 0.0, 0.04], up=[0, -1, 0]))
    uv = CAM.project(X @ T[:3, :3].T + T[:3, 3])
    tgt = tmp_path / "t3d.yaml"
    tgt.write_text("type: points3d\npoints_mm:\n" + "".join(
        f"  {i}: [{x * 1e3:.6f}, {y * 1e3:.6f}, {z * 1e3:.6f}]\n" for i, (x, y, z) in enumerate(X)))
    obs = tmp_path / "obs.csv"
    obs.write_text("id,u_px,v_px\n" + "".join(f"{i},{u:.6f},{v:.6f}\n" for i, (u, v) in enumerate(uv)))
    return tgt, obs


def test_calib_dlt(tmp_path: Path) -> None:
    tgt, obs = _points3d(tmp_path)
    out = tmp_path / "cam.json"
    assert main(["calib", "dlt", "--target", str(tgt), "--points", str(obs), "--out", str(out),
                 "--width", "640", "--height", "480"]) == 0
    cam = json.loads(out.read_text())
    assert np.allclose(cam["K"], CAM.K, atol=0.05)
    assert cam["dist"][0] == pytest.approx(-0.2, abs=1e-3)


def test_calib_dlt_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tgt, obs = _points3d(tmp_path, coplanar=True)
    assert main(["calib", "dlt", "--target", str(tgt), "--points", str(obs)]) == 2
    assert "coplanar" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("u,v\n1,2\n")
    assert main(["calib", "dlt", "--target", str(tgt), "--points", str(bad)]) == 2
    assert "id,u_px,v_px" in capsys.readouterr().err
    bad.write_text("id,u_px,v_px\n999,1,2\n")
    assert main(["calib", "dlt", "--target", str(tgt), "--points", str(bad)]) == 2
    assert "not in the target" in capsys.readouterr().err
    board = tmp_path / "b.yaml"
    board.write_text("type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 20.0\n")
    assert main(["calib", "dlt", "--target", str(board), "--points", str(obs)]) == 2
    assert "points3d" in capsys.readouterr().err
