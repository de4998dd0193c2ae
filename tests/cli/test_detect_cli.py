"""``cellctl detect``: the real console script on rendered and real images, and on bad input."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform
from calibration.targets import CirclePlate
from drivers.sim.imaging import Imaging, PlanarObject, render
from tests.support.cli import run_cli, run_process

DATA = Path(__file__).resolve().parents[2] / "tests" / "data"
PLATE_YAML = "type: circle_plate\ncols: 7\nrows: 7\npitch_mm: 12.5\ndiameter_mm: 6.25\n"


run = run_cli  # the same main() in-process; run_process: the console script, once


def _plate_image(path: Path) -> None:
    plate = CirclePlate(7, 7, 12.5, 6.25)
    cam = CameraModel("opencv5", 640, 480, np.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]]))
    T = make_transform(np.eye(3), [-0.0375, -0.0375, 0.2])
    img = render(cam, [PlanarObject(T, plate.reflectance)], Imaging(noise_sigma=1.0, blur_sigma_px=0.7),
                 np.random.default_rng(0), supersample=4)
    cv2.imwrite(str(path), img)


def test_detect_plate_json_and_out_file(tmp_path: Path) -> None:
    target = tmp_path / "plate.yaml"
    target.write_text(PLATE_YAML)
    image = tmp_path / "plate.png"
    _plate_image(image)
    out = tmp_path / "det.json"
    r = run_process("detect", "--target", str(target), str(image), "--out", str(out))
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert json.loads(out.read_text()) == result
    assert len(result) == 1 and result[0]["found"] is True
    pts = result[0]["points"]
    assert [p["id"] for p in pts] == list(range(49))
    assert set(pts[0]) >= {"id", "u_px", "v_px", "u_ellipse_px", "v_ellipse_px"}
    # frontal view centred on the plate: mark (0,0) at the principal point minus 3 pitches
    assert abs(pts[0]["u_px"] - (320 - 700 * 0.0375 / 0.2)) < 0.05
    assert abs(pts[24]["u_px"] - 320) < 0.05 and abs(pts[24]["v_px"] - 240) < 0.05


def test_detect_real_chessboards(tmp_path: Path) -> None:
    target = tmp_path / "cb.yaml"
    target.write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 1.0\n")
    folder = DATA / "udacity_camera_cal_9x6"
    r = run("detect", "--target", str(target), str(folder / "calibration2.jpg"), str(folder / "calibration4.jpg"))
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res[0]["found"] is True and len(res[0]["points"]) == 54
    assert res[1]["found"] is False and "cropped" in res[1]["reason"]


def _one_line_error(r: subprocess.CompletedProcess[str], *words: str) -> None:
    assert r.returncode != 0
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("cellctl: error:")
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in lines[0]


def test_bad_input_gives_one_line_errors(tmp_path: Path) -> None:
    target = tmp_path / "plate.yaml"
    target.write_text(PLATE_YAML)
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    _one_line_error(run("detect", "--target", str(target), str(corrupt)), "corrupt.png", "cannot decode")
    _one_line_error(run("detect", "--target", str(target), str(empty)), "empty.png", "empty")
    _one_line_error(run("detect", "--target", str(target), str(tmp_path / "nope.png")), "nope.png")
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("type: circle_plates\ncols: 7\nrows: 7\npitch_mm: 12.5\ndiameter_mm: 6.25\n")
    _one_line_error(run("detect", "--target", str(wrong), str(corrupt)), "wrong.yaml", "type")
    pts3d = tmp_path / "p3.yaml"
    pts3d.write_text("type: points3d\npoints_mm:\n" + "".join(f"  {i}: [{i}, 0, {i % 2}]\n" for i in range(6)))
    _one_line_error(run("detect", "--target", str(pts3d), str(corrupt)), "points3d")
