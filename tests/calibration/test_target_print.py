"""Printable targets: true scale, the same pattern as the renderer's reflectance, detectable."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.detect import detect
from calibration.report import (
    MM_PER_INCH,
    TargetPrintError,
    page_origin_px,
    png_bytes,
    png_dpi,
    to_image,
    to_pdf,
    to_svg,
    write_target,
)
from calibration.targets import Charuco, Chessboard, CircleGrid, CirclePlate, PlanarTarget, Points3D

TARGETS: list[PlanarTarget] = [
    Chessboard(9, 6, 20.0),
    Charuco(6, 5, 20.0, 15.0, "DICT_5X5_100"),
    CirclePlate(7, 7, 12.5, 6.25),
    CircleGrid(4, 11, 10.0, 6.0, asymmetric=True),
]


@pytest.mark.parametrize("target", TARGETS, ids=lambda t: t.type)
def test_png_pattern_equals_reflectance_and_detects_in_place(target: PlanarTarget) -> None:
    dpi = 200.0
    img = to_image(target, dpi)
    ou, ov = page_origin_px(target, dpi)
    s = dpi / MM_PER_INCH * 1e3  # px per metre
    # compare with the reflectance at pixel centres away from edges
    x0, y0, x1, y1 = target.extent_m()
    rng = np.random.default_rng(0)
    x = rng.uniform(x0, x1, 4000)
    y = rng.uniform(y0, y1, 4000)
    u = np.rint(ou + x * s).astype(int)
    v = np.rint(ov + y * s).astype(int)
    xc, yc = (u - ou) / s, (v - ov) / s
    r = target.reflectance(xc, yc)
    eps = 1.5 / s
    nb = [target.reflectance(xc + dx, yc + dy) for dx in (-eps, eps) for dy in (-eps, eps)]
    uniform = np.all([np.nan_to_num(n, nan=-1) == np.nan_to_num(r, nan=-1) for n in nb], axis=0) & np.isfinite(r)
    assert uniform.sum() > 2000
    assert np.array_equal(img[v[uniform], u[uniform]] > 127, r[uniform] > 0.5)
    # detect on the plate without the caption strip: OpenCV's circle grid finder can take the
    # caption's letters for circles (seen at 200 dpi), which is OpenCV's limit, not the print's
    plate_bottom = int(np.ceil(ov + y1 * s)) + 2
    det = detect(img[:plate_bottom], target)
    assert det.found, det.reason
    expected = np.array([ou, ov]) + target.points().xyz_m[:, :2] * s
    assert np.hypot(*(det.uv - expected[det.ids]).T).max() < 0.25


def test_svg_and_pdf_sizes_are_exact() -> None:
    t = CirclePlate(5, 4, 20.0, 10.0)
    w_mm = 20.0 * 8 + 10
    h_mm = 20.0 * 7 + 10 + 10
    svg = to_svg(t)
    assert f'width="{w_mm:.4f}mm" height="{h_mm:.4f}mm" viewBox="0 0 {w_mm:.4f} {h_mm:.4f}"' in svg
    assert svg.count("<circle") == 20
    pdf = to_pdf(t)
    m = re.search(rb"/MediaBox \[ ?0 0 ([0-9.]+) ([0-9.]+) ?\]", pdf)
    assert m is not None
    assert abs(float(m.group(1)) - w_mm / 25.4 * 72) < 1e-3 and abs(float(m.group(2)) - h_mm / 25.4 * 72) < 1e-3
    # the cross-reference table points at each object
    xref = int(re.search(rb"startxref\n(\d+)", pdf).group(1))  # type: ignore[union-attr]
    assert pdf[xref : xref + 4] == b"xref"
    offsets = [int(o) for o in re.findall(rb"(\d{10}) 00000 n", pdf)]
    assert len(offsets) >= 5
    for i, off in enumerate(offsets, start=1):
        assert pdf[off:].startswith(b"%d 0 obj" % i)
    # drawn at true scale: 20 circles of 10 mm at a 20 mm pitch, in points of 1/72 inch
    pt = 72.0 / 25.4
    circles = [s for s in _pdf_subpaths(pdf) if s[1]]
    assert len(circles) == 20
    boxes = np.array([[*p.min(axis=0), *p.max(axis=0)] for p, _ in circles])
    assert np.allclose(boxes[:, 2] - boxes[:, 0], 10.0 * pt, atol=1e-3)
    assert np.allclose(boxes[:, 3] - boxes[:, 1], 10.0 * pt, atol=1e-3)
    xs = np.unique(np.round((boxes[:, 0] + boxes[:, 2]) / 2, 3))
    assert len(xs) == 5 and np.allclose(np.diff(xs), 20.0 * pt, atol=1e-3)
    assert b"/FontFile2" in pdf  # the caption's font travels with the file
    # a chessboard's squares: every one of them, 25 mm wide and high, at its place on the page
    quads = [p for p, curved in _pdf_subpaths(to_pdf(Chessboard(9, 6, 25.0))) if not curved and len(p) == 4]
    squares = [p for p in quads if np.allclose(np.ptp(p, axis=0), 25.0 * pt, atol=1e-3)]
    assert len(squares) == sum(1 for j in range(-1, 6) for i in range(-1, 9) if (i + j) % 2 == 0)
    assert len(quads) == len(squares) + 2  # and the page's white and the scale bar


def _pdf_subpaths(pdf: bytes) -> list[tuple[np.ndarray, bool]]:
    """The filled subpaths of a PDF's (deflated) content streams: their points, and whether they curve."""
    out = []
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", pdf, re.S):
        try:
            ops = zlib.decompress(m.group(1)).decode("latin-1")
        except zlib.error:
            continue
        for sub in re.findall(r"(\S+ \S+ m\n(?:(?:\S+ )+[lc]\n)+h)", ops):
            nums = [float(x) for x in re.findall(r"-?\d+\.?\d*", sub)]
            out.append((np.array(nums).reshape(-1, 2), " c\n" in sub))
    return out


def test_png_records_its_dpi(tmp_path: Path) -> None:
    data = png_bytes(np.full((10, 20), 255, dtype=np.uint8), 600.0)
    assert abs(png_dpi(data) - 600.0) < 0.05  # type: ignore[operator]
    p = tmp_path / "x.png"
    p.write_bytes(data)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (10, 20)


def test_refusals(tmp_path: Path) -> None:
    with pytest.raises(TargetPrintError, match="points3d"):
        to_svg(Points3D({i: (float(i), 0.0, float(i % 2)) for i in range(6)}))
    with pytest.raises(TargetPrintError, match=".svg, .pdf or .png"):
        write_target(Chessboard(9, 6, 20.0), tmp_path / "x.gif")
    with pytest.raises(TargetPrintError, match="dpi"):
        to_image(Chessboard(9, 6, 20.0), 3)
