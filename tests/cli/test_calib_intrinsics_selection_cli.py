"""``cellctl calib intrinsics`` chooses the board warp and the lens model by cross-validation
(issue 39): a bowed board gets its warp, a flat one does not, and the report shows both."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.intrinsics.views import warp_basis
from calibration.observations import Detection
from calibration.synthetic import plan_views
from calibration.targets import Chessboard
from tests.support.cli import run_cli

TRUTH = CameraModel("opencv5", 960, 720, np.array([[800.0, 0, 483.0], [0, 798.0, 356.0], [0, 0, 1]]),
                    np.array([-0.28, 0.09, 0.0008, -0.0006, -0.015]))
BOARD = Chessboard(9, 6, 30.0)
TARGET_YAML = "type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 30.0\n"


def _write(tmp: Path, warp_m: tuple[float, float], seed: int) -> tuple[Path, Path]:
    rng = np.random.default_rng(seed)
    tp = BOARD.points()
    X = tp.xyz_m.copy()
    X[:, 2] += warp_basis(BOARD, X) @ np.asarray(warp_m)
    dets = []
    for k, T in enumerate(plan_views(TRUTH, BOARD, 14, rng, fill=0.6, margin_px=6, whole_outline=True)):
        uv = TRUTH.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.05, (len(X), 2))
        dets.append(Detection(f"v{k:02d}.png", True, ids=tp.ids.copy(), uv=uv, image_size=(960, 720)).to_json())
    (tmp / "board.yaml").write_text(TARGET_YAML)
    (tmp / "det.json").write_text(json.dumps(dets))
    return tmp / "board.yaml", tmp / "det.json"


def test_a_bowed_board_gets_its_warp_by_cross_validation_and_the_report_shows_it(tmp_path: Path) -> None:
    target, det = _write(tmp_path, (0.002, -0.001), seed=21)
    rep = tmp_path / "r.html"
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--report", str(rep))
    cam = json.loads(p.stdout)
    assert p.returncode == (0 if cam["verdict"]["ok"] else 3), p.stderr   # 3: a NOT OK verdict (corner coverage)
    sel = cam["model_selection"]
    assert sel["chosen"] == {"model": "opencv5", "board_warp": True}
    by = {c["board_warp"]: c for c in sel["candidates"]}
    assert by[True]["cross_validation_px"] < 0.9 * by[False]["cross_validation_px"]
    assert by[True]["rms_px"] < by[False]["rms_px"]
    assert abs(cam["board_warp"]["height_mm"][0] - 2.0) < 0.3 and abs(cam["board_warp"]["height_mm"][1] + 1.0) < 0.3
    assert cam["cross_validation"]["k"] == 2 and cam["cross_validation"]["projection_difference_rms_px"] > 0
    # the median over the partitions the automatic rule drew: the warp's gain is plain, so it stops early
    n = sel["repeats"]
    assert cam["cross_validation"]["repeats"] == n and 3 <= n < 8 and sel["repeats_rule"].startswith("auto")
    assert all("max_px" in v for v in cam["views"])
    html = rep.read_text()
    assert "board warp" in html and "Model chosen by cross-validation" in html
    assert f"median over {n} partitions of the views" in html


def test_a_flat_board_stays_flat_and_off_means_off(tmp_path: Path) -> None:
    target, det = _write(tmp_path, (0.0, 0.0), seed=22)
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det))
    cam = json.loads(p.stdout)
    assert p.returncode == (0 if cam["verdict"]["ok"] else 3), p.stderr
    assert cam["model_selection"]["chosen"]["board_warp"] is False and "board_warp" not in cam
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--board-warp", "off",
                "--cross-validate", "0")
    cam = json.loads(p.stdout)
    assert p.returncode == (0 if cam["verdict"]["ok"] else 3) and "model_selection" not in cam
    assert "cross_validation" not in cam


def test_model_auto_needs_cross_validation(tmp_path: Path) -> None:
    target, det = _write(tmp_path, (0.0, 0.0), seed=23)
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--model", "auto",
                "--cross-validate", "0")
    assert p.returncode != 0 and "--model auto chooses by cross-validation" in p.stderr


def test_cross_validation_repeats_are_the_users_choice(tmp_path: Path) -> None:
    target, det = _write(tmp_path, (0.0, 0.0), seed=24)
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--board-warp", "off",
                "--cross-validate-repeats", "3")
    cam = json.loads(p.stdout)
    cv = cam["cross_validation"]
    assert cv["repeats"] == 3 and len(cv["per_partition_rms_px"]) == 3 and not cv["failed"]
    assert cv["repeats_rule"] == "fixed"
    assert abs(cv["projection_difference_rms_px"] - sorted(cv["per_partition_rms_px"])[1]) < 1e-6  # median of 3
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--cross-validate-repeats",
                "0")
    assert p.returncode != 0 and "--cross-validate-repeats R needs R >= 1" in p.stderr
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--cross-validate-repeats",
                "many")
    assert p.returncode != 0 and "needs a count R >= 1 or auto, not 'many'" in p.stderr
