"""``cellctl calib intrinsics --regularise``: mrcal's regularised solve, its weights in the result, a clear
refusal for a model without one, and ``--model auto`` trying opencv8 regularised before opencv8 free."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.observations import Detection
from calibration.synthetic import plan_views
from calibration.targets import Chessboard
from cellctl.cli.calib_intrinsics import _candidates
from tests.support.cli import run_cli

TRUTH = CameraModel("opencv5", 960, 720, np.array([[800.0, 0, 483.0], [0, 798.0, 356.0], [0, 0, 1]]),
                    np.array([-0.28, 0.09, 0.0008, -0.0006, -0.015]))
BOARD = Chessboard(9, 6, 30.0)


def test_auto_tries_opencv8_regularised_before_opencv8_free() -> None:
    args = argparse.Namespace(model="auto", export_opencv=None, export_ros=None, board_warp="off", regularise=False)
    assert _candidates(args) == [("division", False, False), ("opencv5", False, False), ("fisheye4", False, False),
                                 ("opencv8", False, True), ("opencv8", False, False), ("splined", False, False)]
    args = argparse.Namespace(model="opencv8", export_opencv=None, export_ros=None, board_warp="auto", regularise=True)
    assert _candidates(args) == [("opencv8", False, True), ("opencv8", True, True)]


def test_regularise_solves_with_mrcals_weights_and_refuses_a_model_without_them(tmp_path: Path) -> None:
    rng = np.random.default_rng(31)
    tp = BOARD.points()
    dets = []
    for k, T in enumerate(plan_views(TRUTH, BOARD, 8, rng, fill=0.6, margin_px=6, whole_outline=True)):
        uv = TRUTH.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.1, (len(tp.ids), 2))
        dets.append(Detection(f"v{k:02d}.png", True, ids=tp.ids.copy(), uv=uv, image_size=(960, 720)).to_json())
    (tmp_path / "board.yaml").write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 30.0\n")
    (tmp_path / "det.json").write_text(json.dumps(dets))
    common = ("calib", "intrinsics", "--target", str(tmp_path / "board.yaml"), "--detections",
              str(tmp_path / "det.json"), "--board-warp", "off", "--cross-validate", "0", "--regularise")
    p = run_cli(*common, "--model", "opencv8")
    cam = json.loads(p.stdout)
    assert p.returncode == (0 if cam["verdict"]["ok"] else 3), p.stderr
    reg = cam["regularisation"]
    n = cam["n_points_used"] * 2
    w_d = np.sqrt(n * 0.0025 / (8 * 4.0))
    assert reg["weights_px"]["k1"] == round(w_d, 6) and reg["weights_px"]["k4"] == round(5 * w_d, 6)
    assert reg["weights_px"]["fx"] == 0.0 and 0.0 < reg["cost_share"] < 0.01
    assert np.max(np.abs(cam["dist"][5:])) < 0.1, cam["dist"]
    p = run_cli(*common, "--model", "fisheye4")
    assert p.returncode != 0 and "fisheye4 model has no regularised solve" in p.stderr, p.stderr
