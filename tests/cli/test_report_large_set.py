"""The report on a large calibration set (3,000+ points): residuals binned per cell, colour bars in
px anchored to the limits, the summary's figures rounded and equal to the plotted ones."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.intrinsics import calibrate
from calibration.report import MAX_VECTORS, write_report
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard
from calibration.verdict import MAX_PROJECTION_RMS_PX

CAM = CameraModel("opencv5", 1280, 960, np.array([[1100.0, 0, 641], [0, 1100.0, 479], [0, 0, 1]]),
                  np.array([-0.15, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(9, 6, 25.0)


def test_large_set_is_binned_and_scaled_to_the_limits(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    dets = synthetic_detections(CAM, BOARD, plan_views(CAM, BOARD, 70, rng), 0.1, rng)
    res = calibrate(dets, BOARD, "opencv5")
    n_points = sum(len(v.uv) for v in res.views if v.used)
    assert n_points > MAX_VECTORS
    out = tmp_path / "r.html"
    write_report(res, out)
    html = out.read_text()
    residuals = re.search(r'<svg class="plot residuals".*?</svg>', html, re.S)
    assert residuals is not None
    svg = residuals.group(0)
    assert "binned" in svg and "colourbar" in svg
    # Binned: one mean arrow per cell, not one per point.
    arrows = re.findall(r'<path [^>]*class="mean-arrows"', svg)
    assert 0 < len(arrows) <= 16 * 12
    # The uncertainty colour bar runs from 0 to twice the verdict's limit, the limit marked on it.
    unc = re.search(r'<svg class="plot uncertainty".*?</svg>', html, re.S)
    assert unc is not None
    bar = ET.fromstring(unc.group(0)).find(".//{*}g[@class='colourbar-axis']")
    assert bar is not None and float(bar.get("data-top", "nan")) == 2 * MAX_PROJECTION_RMS_PX
    ticks = [float(t.text or "nan") for t in bar.iterfind(".//{*}text[@class='tick']")]
    assert ticks and max(ticks) == 2 * MAX_PROJECTION_RMS_PX
    assert ">limit</text>" in unc.group(0)
    # The summary's numbers are the result's, rounded to 3 significant figures.
    assert f"<td class='num'>{res.rms_px:.3g} px</td>" in html or f"{res.rms_px:.3f}" in html
    assert not re.search(r"\d\.\d{7,}", re.sub(r"<(svg|path|style)[^>]*>.*?</\1>|<[^>]+>", " ", html, flags=re.S))
