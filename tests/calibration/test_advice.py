"""Advice that is right: each verdict / refusal message checked against the model and the data.

- no "fewer coefficients" for the one-coefficient division model or a wide-angle lens;
- cross-validation with k too large for the usable views says so, and the calibration stands;
- views of another image size are listed as rejected with the reason (stderr in the CLI);
- a target file that matches none of the images is named as the likely mistake.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.intrinsics import CrossValidationError, IntrinsicsError, calibrate, cross_validate
from calibration.observations import Detection
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard
from calibration.verdict import assess, horizontal_fov_deg
from cellctl.cli import main

BOARD = Chessboard(8, 6, 20.0)
CAM = CameraModel("opencv5", 640, 480, np.array([[600.0, 0, 322], [0, 600, 238], [0, 0, 1]]),
                  np.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
TARGET_YAML = "type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 20.0\n"


def _dets(n: int, seed: int = 4) -> list[Detection]:
    rng = np.random.default_rng(seed)
    return synthetic_detections(CAM, BOARD, plan_views(CAM, BOARD, n, rng), 0.1, rng)


def _uncertain_advice(model: str, fx: float, size: tuple[int, int] = (1280, 960)) -> str:
    cov = np.zeros((16, 16), dtype=np.int64)
    cov[:] = 5
    v = assess(n_views=12, size=size, coverage=cov, normals=np.array([[0.4, 0.0, 0.9], [0.0, 0.4, 0.9]]),
               sigmas={}, values={"fx": fx, "fy": fx}, uncertainty={"projection_rms_px": 1.3}, model=model)
    (msg,) = [p["message"] for p in v["problems"] if p["code"] == "projection_uncertain"]
    return msg


def test_no_fewer_coefficients_for_division() -> None:
    msg = _uncertain_advice("division", fx=1100.0)
    assert "fewer" not in msg and "instead of" not in msg
    assert "single distortion coefficient" in msg and "add views" in msg


def test_no_fewer_coefficients_for_a_wide_angle_lens() -> None:
    assert horizontal_fov_deg((1280, 960), 500.0) > 90
    for model in ("opencv5", "opencv8"):
        msg = _uncertain_advice(model, fx=500.0)
        assert "wide-angle" in msg and "do not drop coefficients" in msg
        assert "choose opencv5" not in msg and "1 coefficient instead" not in msg


def test_fewer_coefficients_offered_where_the_model_has_some_to_spare() -> None:
    assert "choose opencv5" in _uncertain_advice("opencv8", fx=1100.0)
    assert "choose the division model" in _uncertain_advice("opencv5", fx=1100.0)


def test_cross_validation_k_too_large_says_so() -> None:
    dets = _dets(15)
    for d in dets[:4]:  # four views the calibration cannot use: 11 usable, too few for 5 folds of 3
        d.found, d.reason = False, "target not found"
    with pytest.raises(CrossValidationError, match="k = 5 is too large for 11 views") as err:
        cross_validate(dets, BOARD, "opencv5", k=5)
    assert "use k <= 3" in str(err.value)
    cv = cross_validate(dets, BOARD, "opencv5", k=3)
    assert cv["k"] == 3 and len(cv["pairs"]) == 3


def test_view_of_another_size_rejected_with_reason() -> None:
    dets = _dets(10)
    dets[3].image_size = (641, 481)
    res = calibrate(dets, BOARD, "opencv5")
    rej = res.to_json()["rejected_views"]
    assert [r["image"] for r in rej] == [dets[3].image]
    assert "641x481" in rej[0]["reason"] and "640x480" in rej[0]["reason"]


def test_wrong_target_is_named() -> None:
    dets = [Detection(f"v{k}.png", False, reason="no 9x6 chessboard found", image_size=(640, 480))
            for k in range(6)]
    with pytest.raises(IntrinsicsError, match="found in none of the 6 images") as err:
        calibrate(dets, Chessboard(9, 6, 25.0), "opencv5")
    assert "target file" in str(err.value) and "image_size" not in str(err.value)


def _write(tmp_path: Path, dets: list[Detection]) -> tuple[str, str]:
    det = tmp_path / "det.json"
    det.write_text(json.dumps([d.to_json() for d in dets]))
    target = tmp_path / "board.yaml"
    target.write_text(TARGET_YAML)
    return str(det), str(target)


def test_cli_reports_rejected_views_and_a_too_large_k_on_stderr(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    dets = _dets(12)
    dets[5].image_size = (1281, 721)
    det, target = _write(tmp_path, dets)
    capsys.readouterr()
    rc = main(["calib", "intrinsics", "--target", target, "--detections", det, "--cross-validate", "5"])
    cap = capsys.readouterr()
    assert rc == (0 if json.loads(cap.out)["verdict"]["ok"] else 3)  # 3: a NOT OK verdict (issue 36)
    assert f"view rejected: {dets[5].image}: image size 1281x721" in cap.err
    assert "cross-validation not run: k = 5 is too large for 11 views" in cap.err
    out = json.loads(cap.out)
    assert out["cross_validation"]["k"] == 5 and "too large" in out["cross_validation"]["error"]
    assert out["n_views_used"] == 11 and "fx" in out["parameters"]["names"]
