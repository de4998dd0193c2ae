"""``cellctl calib intrinsics`` / ``calib export`` / ``calib import`` on rendered images, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.intrinsics import projection_difference
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard
from cellctl.cli import main
from drivers.sim.imaging import Imaging, PlanarObject, render
from tests.support.cli import run_cli

CELLCTL = str(Path(sys.executable).parent / "cellctl")
TRUTH = CameraModel("opencv5", 640, 480, np.array([[600.0, 0, 322], [0, 600, 238], [0, 0, 1]]),
                    np.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 20.0)
TARGET_YAML = "type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 20.0\n"


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("views")
    rng = np.random.default_rng(3)
    for k, T in enumerate(plan_views(TRUTH, BOARD, 8, rng, margin_px=25)):
        img = render(TRUTH, [PlanarObject(T, BOARD.reflectance)], Imaging(noise_sigma=2.0, blur_sigma_px=0.6), rng)
        cv2.imwrite(str(d / f"view{k:02d}.png"), img)
    (d / "notes.txt").write_text("not an image")
    (d.parent / "board.yaml").write_text(TARGET_YAML)
    return d


def test_folder_to_report_and_opencv_yaml(image_dir: Path, tmp_path: Path) -> None:
    out, rep, yml = tmp_path / "cam.json", tmp_path / "r.html", tmp_path / "cam.yaml"
    p = run_cli("calib", "intrinsics", "--target", str(image_dir.parent / "board.yaml"),
                "--model", "opencv5", str(image_dir), "--out", str(out), "--report", str(rep),
                "--export-opencv", str(yml), "--cross-validate", "2")
    cam = json.loads(out.read_text())
    assert p.returncode == (0 if cam["verdict"]["ok"] else 3), p.stderr  # 3: the verdict is NOT OK (issue 36)
    assert json.loads(p.stdout) == cam
    assert cam["model"] == "opencv5" and len(cam["views"]) == 8 and all(v["used"] for v in cam["views"])
    assert cam["rms_px"] < 0.2
    assert 0 < cam["uncertainty"]["projection_rms_px"] < 0.2
    assert "ok" in cam["verdict"] and "cross_validation" in cam
    est = CameraModel.from_dict(cam)
    assert projection_difference(est, TRUTH)["rms_px"] < 0.5
    html = rep.read_text()
    assert html.count('<svg class="plot') == 7 and "Projection uncertainty" in html  # 7: residuals against the radius
    assert html.count('<svg class="plot radius"') == 1
    assert html.count("<figure class='thumb") == 8 and html.count("data:image/jpeg;base64,") == 8
    from calibration.io import read_opencv_yaml

    assert np.allclose(read_opencv_yaml(yml).K, est.K)
    for prob in cam["verdict"]["problems"]:
        assert prob["code"] in p.stderr


def _detections_file(tmp_path: Path, n: int, model: CameraModel = TRUTH, noise: float = 0.1) -> Path:
    rng = np.random.default_rng(5)
    dets = synthetic_detections(model, BOARD, plan_views(model, BOARD, n, rng), noise, rng)
    f = tmp_path / "det.json"
    f.write_text(json.dumps([d.to_json() for d in dets]))
    (tmp_path / "board.yaml").write_text(TARGET_YAML)
    return f


def test_detections_input_division_and_halcon_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    div = CameraModel("division", 640, 480, TRUTH.K, np.array([-0.2]))
    det = _detections_file(tmp_path, 12, div)
    hal = tmp_path / "cam.cal"
    rc = main(["calib", "intrinsics", "--target", str(tmp_path / "board.yaml"), "--model", "division",
               "--detections", str(det), "--export-halcon", str(hal), "--pixel-pitch-um", "3.45",
               "--out", str(tmp_path / "cam.json")])
    assert rc == 0
    cam = json.loads((tmp_path / "cam.json").read_text())
    assert cam["dist"][0] == pytest.approx(-0.2, abs=0.01)
    assert "area_scan_division" in hal.read_text()
    capsys.readouterr()
    rc = main(["calib", "export", "--camera", str(tmp_path / "cam.json"), "--format", "opencv",
               "--out", str(tmp_path / "x.yaml")])
    assert rc == 2
    assert "division" in capsys.readouterr().err
    rc = main(["calib", "import", str(hal), "--format", "halcon", "--out", str(tmp_path / "back.json")])
    assert rc == 0
    back = json.loads((tmp_path / "back.json").read_text())
    assert np.allclose(back["K"], cam["K"]) and np.allclose(back["dist"], cam["dist"])


def test_export_import_round_trip_cli(tmp_path: Path) -> None:
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(TRUTH.to_dict()))
    for fmt in ("opencv", "ros"):
        f = tmp_path / f"{fmt}.yaml"
        assert main(["calib", "export", "--camera", str(cam), "--format", fmt, "--out", str(f)]) == 0
        out = tmp_path / f"{fmt}.json"
        assert main(["calib", "import", str(f), "--format", fmt, "--out", str(out)]) == 0
        back = json.loads(out.read_text())
        assert np.allclose(back["K"], TRUTH.K) and np.allclose(back["dist"], TRUTH.dist)


@pytest.mark.parametrize("case", ["no_images", "missing_file", "too_few_views", "bad_target", "bad_detections",
                                  "halcon_wrong_model", "cv_k1"])
def test_bad_input_clear_error(tmp_path: Path, case: str, capsys: pytest.CaptureFixture[str]) -> None:
    det = _detections_file(tmp_path, 12)
    target = str(tmp_path / "board.yaml")
    args = {
        "no_images": ["--target", target],
        "missing_file": ["--target", target, str(tmp_path / "nope.png")],
        "too_few_views": ["--target", target, "--detections", str(_few(tmp_path, det))],
        "bad_target": ["--target", str(det), "--detections", str(det)],
        "bad_detections": ["--target", target, "--detections", target],
        "halcon_wrong_model": ["--target", target, "--detections", str(det), "--export-halcon", "x.cal"],
        "cv_k1": ["--target", target, "--detections", str(det), "--cross-validate", "1"],
    }[case]
    capsys.readouterr()
    assert main(["calib", "intrinsics", *args]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("cellctl: error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err


def test_console_script_bad_input_exits_2_without_traceback(tmp_path: Path) -> None:
    p = subprocess.run([CELLCTL, "calib", "intrinsics", "--target", str(tmp_path / "missing.yaml"), "x.png"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1].startswith("cellctl: error:")
    assert "missing.yaml" in p.stderr and "Traceback" not in p.stderr


def _few(tmp_path: Path, det: Path) -> Path:
    data = json.loads(det.read_text())[:2]
    f = tmp_path / "few.json"
    f.write_text(json.dumps(data))
    return f


@pytest.mark.parametrize(("content", "words"), [
    (b'{"image": "a.png", "points": []}', "holds a JSON object"),
    (b"[1, 2]", "entries are not detections"),
    (bytes(range(256)) * 4, "not a text file"),
    (b"[{", "not valid JSON"),
])
def test_detections_that_are_not_a_detection_list_are_one_line(tmp_path: Path, content: bytes, words: str) -> None:
    det = tmp_path / "det.json"
    det.write_bytes(content)
    target = tmp_path / "board.yaml"
    target.write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 25\n")
    r = run_cli("calib", "intrinsics", "--target", str(target), "--model", "opencv5", "--detections", str(det))
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert str(det) in lines[0] and words in lines[0] and "cellctl detect" in lines[0]


def test_a_not_ok_verdict_exits_3_with_the_result_written(tmp_path: Path) -> None:
    """As `job run --follow`: exit 3 when the calibration ran but its verdict is NOT OK (5 views: too few);
    the camera JSON is still written to stdout and --out."""
    det = _detections_file(tmp_path, 5)
    out = tmp_path / "cam.json"
    p = run_cli("calib", "intrinsics", "--target", str(tmp_path / "board.yaml"), "--detections", str(det),
                "--out", str(out))
    assert p.returncode == 3, p.stderr
    cam = json.loads(out.read_text())
    assert cam["verdict"]["ok"] is False and json.loads(p.stdout) == cam
    assert "too_few_views" in p.stderr and "verdict NOT OK" in p.stderr.strip().splitlines()[-1]
    ok = run_cli("calib", "intrinsics", "--target", str(tmp_path / "board.yaml"),
                 "--detections", str(_detections_file(tmp_path, 12)))
    assert ok.returncode == 0 and json.loads(ok.stdout)["verdict"]["ok"] is True, ok.stderr
