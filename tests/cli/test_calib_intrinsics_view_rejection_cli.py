"""``cellctl calib intrinsics`` rejects an influential view by default (issue 39): the reason on
stderr, in cam.json and in the report; ``--reject-views off`` keeps every view."""

from __future__ import annotations

import json
from pathlib import Path

from tests.calibration.test_view_influence import _shear, _views
from tests.support.cli import run_cli


def test_calib_intrinsics_drops_the_sheared_view_says_why_in_the_report_and_off_keeps_it(tmp_path: Path) -> None:
    """The product's ``calib intrinsics`` runs the test by default: the view's reason on stderr, in
    ``rejected_views`` and ``view_rejection`` of cam.json and in the HTML report; ``--reject-views off``
    keeps every view."""
    dets = _views(3)
    _shear(dets[3], 2.0)
    (tmp_path / "det.json").write_text(json.dumps([d.to_json() for d in dets]))
    (tmp_path / "board.yaml").write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 30.0\n")
    base = ["calib", "intrinsics", "--target", str(tmp_path / "board.yaml"), "--detections",
            str(tmp_path / "det.json"), "--model", "opencv5", "--cross-validate", "0"]
    p = run_cli(*base, "--out", str(tmp_path / "cam.json"), "--report", str(tmp_path / "r.html"))
    assert p.returncode in (0, 3), p.stderr
    assert "view rejected: view03: influential view" in p.stderr, p.stderr
    cam = json.loads((tmp_path / "cam.json").read_text())
    assert [r["image"] for r in cam["view_rejection"]["rejected"]] == ["view03"]
    assert cam["rejected_views"][0]["image"] == "view03" and cam["n_views_used"] == len(dets) - 1
    assert "influential view" in (tmp_path / "r.html").read_text()
    p = run_cli(*base, "--reject-views", "off", "--out", str(tmp_path / "cam_all.json"))
    cam = json.loads((tmp_path / "cam_all.json").read_text())
    assert cam["n_views_used"] == len(dets) and "view_rejection" not in cam
