"""``cellctl target render``: true-scale SVG/PDF/PNG files through the console script."""

from __future__ import annotations

import json
import re
from pathlib import Path

from calibration.report import png_dpi
from tests.support.cli import run_cli, run_process

run = run_cli  # the same main() in-process; run_process: the console script, once


def test_render_each_format(tmp_path: Path) -> None:
    target = tmp_path / "plate.yaml"
    target.write_text("type: circle_plate\ncols: 7\nrows: 7\npitch_mm: 12.5\ndiameter_mm: 6.25\n")
    for ext in ("svg", "pdf", "png"):
        out = tmp_path / f"plate.{ext}"
        runner = run_process if ext == "svg" else run  # the entry point once
        r = runner("target", "render", "--target", str(target), "--out", str(out), "--dpi", "200")
        assert r.returncode == 0, r.stderr
        summary = json.loads(r.stdout)
        # page: the plate (frame inner edge (cols + 1) pitches, frame and white rim one pitch each side)
        # plus 2 x 5 mm page margin; height adds the 10 mm caption strip
        assert summary["width_mm"] == 12.5 * 10 + 10
        assert summary["height_mm"] == 12.5 * 10 + 10 + 10
        assert summary["check"]["length_mm"] == 75.0
        assert out.stat().st_size > 100
    svg = (tmp_path / "plate.svg").read_text()
    assert re.search(r'width="135\.0000mm" height="145\.0000mm"', svg)
    assert "check: mark centres (0,0) to (0,6) = 75.00 mm" in svg
    pdf = (tmp_path / "plate.pdf").read_bytes()
    box = re.search(rb"/MediaBox \[ ?0 0 ([0-9.]+) ([0-9.]+) ?\]", pdf)  # 135 x 145 mm in points
    assert pdf.startswith(b"%PDF-1.4") and box is not None
    assert abs(float(box.group(1)) - 382.6772) < 1e-3 and abs(float(box.group(2)) - 411.0236) < 1e-3
    assert abs(png_dpi((tmp_path / "plate.png").read_bytes()) - 200) < 0.05  # type: ignore[operator]


def test_bad_requests_are_one_line_errors(tmp_path: Path) -> None:
    target = tmp_path / "cb.yaml"
    target.write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 25\n")
    for args, word in [
        (["--out", str(tmp_path / "x.jpg")], ".svg, .pdf or .png"),
        (["--out", str(tmp_path / "x.png"), "--dpi", "5"], "dpi"),
    ]:
        r = run("target", "render", "--target", str(target), *args)
        assert r.returncode != 0
        assert len(r.stderr.strip().splitlines()) == 1 and word in r.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("type: chessboard\ncols: 9\nrows: 6\n")
    r = run("target", "render", "--target", str(bad), "--out", str(tmp_path / "x.svg"))
    assert r.returncode != 0 and "square_mm" in r.stderr and "Traceback" not in r.stderr
