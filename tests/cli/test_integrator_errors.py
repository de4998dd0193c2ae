"""Messages an integrator meets on day one, each one line naming the field and the fix (CLI)."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import shutil
from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.handeye import RobotNoise, calibrate_handeye
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard
from cellctl.cli import main
from tests.conftest import REPO

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))


def _run(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


def _one_line_error(code: int, err: str) -> str:
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cellctl: error: ") and "Traceback" not in err, err
    return lines[0]


def test_calib_import_of_a_file_opencv_cannot_parse(tmp_path: Path) -> None:
    for name, text in (("cam.yaml", "camera_matrix: [unclosed\n"), ("cam.xml", "<<<not xml")):
        f = tmp_path / name
        f.write_text(text)
        line = _one_line_error(*_run("calib", "import", str(f))[::2])
        assert "OpenCV cannot parse it" in line and "--format ros" in line and "persistence.cpp" not in line


@functools.cache
def _he_json() -> str:
    """The hand-eye solved from a simulated set: the same file for both map tests, so solved once per process."""
    board = Chessboard(8, 6, 30.0)
    sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(5), camera=CAM, target=board,
                           robot_noise=RobotNoise(0.05, 0.01))
    res = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, board, leave_one_out=False)
    return json.dumps(res.to_json())


def _he_file(tmp_path: Path) -> Path:
    he = tmp_path / "he.json"
    he.write_text(_he_json())
    (tmp_path / "cam.json").write_text(json.dumps(CAM.to_dict()))
    return he


def test_map_refuses_a_pose_in_millimetres_and_pixels_outside_the_image(tmp_path: Path) -> None:
    he = _he_file(tmp_path)
    cam = str(tmp_path / "cam.json")
    code, _, err = _run("map", "--calib", str(he), "--camera", cam, "--plane-z-mm", "0",
                        "--robot-pose", "534.7,12.0,400.0,3.14,0,0", "800", "600")
    line = _one_line_error(code, err)
    assert "--robot-pose[0] = 534.7 m" in line and "metres" in line
    code, _, err = _run("map", "--calib", str(he), "--camera", cam, "--plane-z-mm", "0",
                        "--robot-pose", "0.5,0,0.4,3.14,0,0", "1700", "600")
    line = _one_line_error(code, err)
    assert "U = 1700" in line and "1600x1200" in line


def test_map_answers_sigma_mm_like_the_rest_api(tmp_path: Path) -> None:
    he = _he_file(tmp_path)
    code, out, err = _run("map", "--calib", str(he), "--camera", str(tmp_path / "cam.json"), "--plane-z-mm", "0",
                          "--robot-pose", "0.5,0,0.45,3.14159,0,0", "800", "600")
    assert code == 0, err
    ans = json.loads(out)
    assert ans["sigma_mm"] == [ans["sigma"]["x_mm"], ans["sigma"]["y_mm"], ans["sigma"]["z_mm"]]


def test_detect_accepts_folders(tmp_path: Path) -> None:
    src = REPO / "tests" / "data" / "udacity_camera_cal_9x6"
    folder = tmp_path / "imgs"
    folder.mkdir()
    for name in ("calibration2.jpg", "calibration3.jpg"):
        shutil.copy(src / name, folder / name)
    (folder / "notes.txt").write_text("not an image")
    target = REPO / "deploy" / "examples" / "targets" / "chessboard-9x6.yaml"
    code, out, err = _run("detect", "--target", str(target), str(folder))
    assert code == 0, err
    res = json.loads(out)
    assert [Path(r["image"]).name for r in res] == ["calibration2.jpg", "calibration3.jpg"]
    assert all(r["found"] and len(r["points"]) == 54 for r in res)
    empty = tmp_path / "empty"
    empty.mkdir()
    line = _one_line_error(*_run("detect", "--target", str(target), str(empty))[::2])
    assert "holds no" in line


def test_example_targets_load_and_render(tmp_path: Path) -> None:
    from calibration.targets import load_target

    files = sorted((REPO / "deploy" / "examples" / "targets").glob("*.yaml"))
    types = {load_target(f).type for f in files}
    assert types == {"chessboard", "charuco", "circle_plate", "circle_grid", "points3d"}
    for f in files:
        assert f.read_text().startswith("# "), f"{f.name}: say what it is in a header comment"
        if load_target(f).type == "points3d":
            continue  # nothing to print
        out = tmp_path / f"{f.stem}.svg"
        code, _, err = _run("target", "render", "--target", str(f), "--out", str(out))
        assert code == 0, err
        assert out.stat().st_size > 500
