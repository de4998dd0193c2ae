"""``cellctl calib intrinsics --model splined``: refused with the reason on a small set, and the
OpenCV/ROS exports refuse the model before any work (issue 39 item 2)."""

from __future__ import annotations

from pathlib import Path

from tests.cli.test_calib_intrinsics_selection_cli import _write
from tests.support.cli import run_cli


def test_the_splined_model_is_refused_on_a_small_set_and_by_the_opencv_export(tmp_path: Path) -> None:
    target, det = _write(tmp_path, (0.0, 0.0), seed=5)
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--model", "splined")
    assert p.returncode != 0 and "at least 40 views" in p.stderr, p.stderr
    p = run_cli("calib", "intrinsics", "--target", str(target), "--detections", str(det), "--model", "splined",
                "--export-opencv", str(tmp_path / "c.yaml"))
    assert p.returncode != 0 and "splined" in p.stderr and not (tmp_path / "c.yaml").exists(), p.stderr
