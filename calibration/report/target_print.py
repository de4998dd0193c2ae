"""Printable calibration targets at true scale: SVG, PDF and PNG (HALCON's plate-making step).

The pattern is drawn from shapes built on the geometry of ``calibration.targets`` and checked
against its ``reflectance`` (the renderer's source) in the tests, so a printed plate, a rendered
one and the detector always agree.

- **SVG**: ``width``/``height`` in ``mm`` and a ``viewBox`` in millimetres: exact size.
- **PDF**: one page by matplotlib's PDF backend, MediaBox in points of 1/72 inch, drawn in
  millimetres (the figure is the page, its one axes fills it): exact size; the caption's font
  embedded.
- **PNG**: the same shapes filled at 4x ``dpi`` and area-averaged (anti-aliased), with the
  resolution recorded in a ``pHYs`` chunk (pixels per metre), written here with zlib.

Below the plate a caption line states the type, the geometry and a check length (the distance
between two named points of the pattern, plus a scale bar) to measure after printing: a printer
that scales the page shows up at once.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.targets import Charuco, Chessboard, CircleGrid, CirclePlate, PlanarTarget, Points3D, Target

MM_PER_INCH: Final = 25.4
CAPTION_MM: Final = 10.0
MARGIN_MM: Final = 5.0
FORMATS: Final = (".svg", ".pdf", ".png")


class TargetPrintError(CalibrationError):
    """The target cannot be printed as asked (3D target, unknown format, absurd resolution).

    ``inputs``: the arguments at fault (``"dpi"``), for a front end to name its own way."""

    def __init__(self, message: str, inputs: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.inputs = inputs


@dataclass(frozen=True)
class Rect:
    x: float
    y: float
    w: float
    h: float


@dataclass(frozen=True)
class Circle:
    cx: float
    cy: float
    r: float


@dataclass(frozen=True)
class Polygon:
    points: tuple[tuple[float, float], ...]


Shape = Rect | Circle | Polygon


def shapes_mm(target: PlanarTarget) -> list[Shape]:
    """The black parts of the pattern in millimetres, target frame (x right, y down)."""
    out: list[Shape] = []
    if isinstance(target, Chessboard):
        s = target.square_mm
        for j in range(-1, target.rows):
            for i in range(-1, target.cols):
                if (i + j) % 2 == 0:
                    out.append(Rect(i * s, j * s, s, s))
    elif isinstance(target, Charuco):
        s = target.square_mm
        o = np.asarray(target.cv_board().getChessboardCorners(), dtype=np.float64)[0] * 1e3
        board = target.cv_board()
        quads = np.asarray(board.getObjPoints(), dtype=np.float64)[:, :, :2] * 1e3 - o[:2]
        d = board.getDictionary()
        bits = d.markerSize + 2
        marker_square = np.zeros((target.rows, target.cols), dtype=bool)
        for quad, mid in zip(quads, board.getIds().ravel(), strict=True):
            x0, y0 = quad[0]
            side = quad[1, 0] - quad[0, 0]
            marker_square[int((y0 + o[1]) // s), int((x0 + o[0]) // s)] = True
            cell = cv2.aruco.generateImageMarker(d, int(mid), bits, borderBits=1)
            b = side / bits
            for br in range(bits):
                for bc in range(bits):
                    if cell[br, bc] < 128:
                        out.append(Rect(x0 + bc * b, y0 + br * b, b, b))
        for j in range(target.rows):
            for i in range(target.cols):
                if not marker_square[j, i]:
                    out.append(Rect(i * s - o[0], j * s - o[1], s, s))
    elif isinstance(target, CirclePlate):
        p = target.pitch_mm
        x0, y0, x1, y1 = -p, -p, target.cols * p, target.rows * p
        w = p / 2
        out += [Rect(x0 - w, y0 - w, x1 - x0 + 2 * w, w), Rect(x0 - w, y1, x1 - x0 + 2 * w, w),
                Rect(x0 - w, y0, w, y1 - y0), Rect(x1, y0, w, y1 - y0)]
        out.append(Polygon(((x0, y0), (x0 + p / 2, y0), (x0, y0 + p / 2))))
        r = target.diameter_mm / 2
        for row in range(target.rows):
            for col in range(target.cols):
                out.append(Circle(col * p, row * p, r))
    elif isinstance(target, CircleGrid):
        r = target.diameter_mm / 2
        for x, y, _ in target.points().xyz_m * 1e3:
            out.append(Circle(float(x), float(y), r))
    else:  # pragma: no cover
        raise TargetPrintError(f"cannot draw a {type(target).__name__}")
    return out


def check_length(target: PlanarTarget) -> tuple[str, float]:
    """(what to measure, its length in mm): the two farthest points of one row of the pattern."""
    if isinstance(target, Chessboard):
        return (f"corner (0,0) to corner (0,{target.cols - 1})", (target.cols - 1) * target.square_mm)
    if isinstance(target, Charuco):
        return (f"corner 0 to corner {target.cols - 2}", (target.cols - 2) * target.square_mm)
    if isinstance(target, CirclePlate):
        return (f"mark centres (0,0) to (0,{target.cols - 1})", (target.cols - 1) * target.pitch_mm)
    xs = target.points().xyz_m[: target.cols, 0] * 1e3
    return (f"circle centres (0,0) to (0,{target.cols - 1})", float(xs.max() - xs.min()))


def caption(target: PlanarTarget) -> str:
    what, length = check_length(target)
    return f"{target.describe()} | check: {what} = {length:.2f} mm"


def _page(target: PlanarTarget) -> tuple[float, float, float, float]:
    """(width_mm, height_mm, offset_x_mm, offset_y_mm): page size and where the target origin lands."""
    x0, y0, x1, y1 = (v * 1e3 for v in target.extent_m())
    width = (x1 - x0) + 2 * MARGIN_MM
    height = (y1 - y0) + 2 * MARGIN_MM + CAPTION_MM
    return width, height, MARGIN_MM - x0, MARGIN_MM - y0


def _scale_bar_mm(width_mm: float) -> float:
    for length in (100.0, 50.0, 20.0, 10.0):
        if length <= 0.4 * width_mm:
            return length
    return 5.0


def _require_planar(target: Target) -> PlanarTarget:
    if isinstance(target, Points3D):
        raise TargetPrintError("points3d targets are 3D objects and cannot be printed; build them and measure "
                               "their points")
    return target


def to_svg(target: Target) -> str:
    """The target as an SVG document at true scale (millimetre user units)."""
    t = _require_planar(target)
    W, H, ox, oy = _page(t)
    x0, y0, x1, y1 = (v * 1e3 for v in t.extent_m())
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W:.4f}mm" height="{H:.4f}mm" '
        f'viewBox="0 0 {W:.4f} {H:.4f}">',
        f'<rect x="0" y="0" width="{W:.4f}" height="{H:.4f}" fill="white"/>',
        f'<rect x="{x0 + ox:.4f}" y="{y0 + oy:.4f}" width="{x1 - x0:.4f}" height="{y1 - y0:.4f}" '
        'fill="none" stroke="#c0c0c0" stroke-width="0.1"/>',
        '<g fill="black" stroke="none">',
    ]
    for s in shapes_mm(t):
        if isinstance(s, Rect):
            parts.append(f'<rect x="{s.x + ox:.4f}" y="{s.y + oy:.4f}" width="{s.w:.4f}" height="{s.h:.4f}"/>')
        elif isinstance(s, Circle):
            parts.append(f'<circle cx="{s.cx + ox:.4f}" cy="{s.cy + oy:.4f}" r="{s.r:.4f}"/>')
        else:
            pts = " ".join(f"{x + ox:.4f},{y + oy:.4f}" for x, y in s.points)
            parts.append(f'<polygon points="{pts}"/>')
    parts.append("</g>")
    cy = H - CAPTION_MM / 2
    bar = _scale_bar_mm(W)
    parts.append(f'<rect x="{MARGIN_MM:.4f}" y="{cy - 2.5:.4f}" width="{bar:.4f}" height="1" fill="black"/>')
    parts.append(f'<text x="{MARGIN_MM:.4f}" y="{cy + 2.5:.4f}" font-family="Helvetica, Arial, sans-serif" '
                 f'font-size="2.5">{_xml(caption(t))} | bar above = {bar:g} mm</text>')
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _xml(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def to_pdf(target: Target) -> bytes:
    """The target as a one-page PDF at true scale, drawn by matplotlib's PDF backend.

    The page is the figure: ``W x H`` mm (MediaBox in points of 1/72 inch), one axes filling it in
    millimetres, y down, no margins; the black shapes are one filled path each kind, without
    outline (a stroke would grow them). The caption's font is embedded (a TrueType subset)."""
    from matplotlib.patches import PathPatch, Rectangle
    from matplotlib.path import Path as MplPath

    from calibration.report.plots import canvas

    t = _require_planar(target)
    W, H, ox, oy = _page(t)
    pt = 72.0 / MM_PER_INCH
    paths = []
    for s in shapes_mm(t):
        if isinstance(s, Rect):
            paths.append(MplPath.unit_rectangle().transformed(_mm(s.w, s.h, s.x + ox, s.y + oy)))
        elif isinstance(s, Circle):
            paths.append(MplPath.unit_circle().transformed(_mm(s.r, s.r, s.cx + ox, s.cy + oy)))
        else:
            paths.append(MplPath(np.array([(x + ox, y + oy) for x, y in s.points] + [(0.0, 0.0)]), closed=True))
    cy = H - CAPTION_MM / 2
    bar = _scale_bar_mm(W)
    with canvas(W * pt, H * pt, layout=None, rc={"pdf.fonttype": 42}) as fig:
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_axis_off()
        ax.set_xlim(0.0, W)
        ax.set_ylim(H, 0.0)
        ax.add_patch(PathPatch(MplPath.make_compound_path(*paths), facecolor="#000", lw=0))
        ax.add_patch(Rectangle((MARGIN_MM, cy - 2.5), bar, 1.0, facecolor="#000", lw=0))
        ax.text(MARGIN_MM, cy + 2.5, f"{caption(t)} | bar above = {bar:g} mm", fontsize=2.5 * pt,
                family="sans-serif", va="baseline")
        buf = io.BytesIO()
        fig.savefig(buf, format="pdf", metadata={"Creator": None, "Producer": None, "CreationDate": None},
                    facecolor="white")
    return buf.getvalue()


def _mm(sx: float, sy: float, tx: float, ty: float) -> Any:
    """The affine that scales a unit shape by (sx, sy) and moves it to (tx, ty), millimetres."""
    from matplotlib.transforms import Affine2D

    return Affine2D().scale(sx, sy).translate(tx, ty)


def to_image(target: Target, dpi: float) -> NDArray[np.uint8]:
    """The printable page as an 8-bit grey image at ``dpi``.

    The shapes of ``shapes_mm`` are filled at 4x the resolution with sub-pixel vertex positions
    and area-averaged down, so each pixel holds its covered fraction (what the renderer's box
    filter does with ``reflectance``).
    """
    t = _require_planar(target)
    if not 10 <= dpi <= 2400:
        raise TargetPrintError(f"dpi must be between 10 and 2400, got {dpi:g}", inputs=("dpi",))
    W, H, ox, oy = _page(t)
    px_per_mm = dpi / MM_PER_INCH
    w, h = int(round(W * px_per_mm)), int(round(H * px_per_mm))
    if w * h > 100e6:
        raise TargetPrintError(f"{w}x{h} pixels is too large; lower the resolution (dpi {dpi:g})", inputs=("dpi",))
    n = 4
    shift = 4
    big = np.full((h * n, w * n), 255, dtype=np.uint8)
    f = px_per_mm * n * (1 << shift)

    def fix(x_mm: float, y_mm: float) -> tuple[int, int]:
        # pixel centres at integer coordinates: a point x_mm maps to x_mm * scale - 0.5
        return int(round(((x_mm + ox) * px_per_mm * n - 0.5) * (1 << shift))), \
            int(round(((y_mm + oy) * px_per_mm * n - 0.5) * (1 << shift)))

    for s in shapes_mm(t):
        if isinstance(s, Rect):
            pts = [(s.x, s.y), (s.x + s.w, s.y), (s.x + s.w, s.y + s.h), (s.x, s.y + s.h)]
        elif isinstance(s, Polygon):
            pts = list(s.points)
        else:
            c = fix(s.cx, s.cy)
            cv2.circle(big, c, int(round(s.r * f)), 0, -1, cv2.LINE_8, shift)
            continue
        poly = np.array([fix(x, y) for x, y in pts], dtype=np.int32)
        cv2.fillPoly(big, [poly], 0, cv2.LINE_8, shift)
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    cy = H - CAPTION_MM / 2
    bar = _scale_bar_mm(W)
    img[int(round((cy - 2.5) * px_per_mm)) : int(round((cy - 1.5) * px_per_mm)),
        int(round(MARGIN_MM * px_per_mm)) : int(round((MARGIN_MM + bar) * px_per_mm))] = 0
    text = f"{caption(t)} | bar above = {bar:g} mm"
    scale = 2.5 * px_per_mm / 22.0  # Hershey simplex cap height is ~22 px at scale 1
    (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    max_w = (W - 2 * MARGIN_MM) * px_per_mm
    if tw > max_w:
        scale *= max_w / tw
    cv2.putText(img, text, (int(round(MARGIN_MM * px_per_mm)), int(round((cy + 2.5) * px_per_mm))),
                cv2.FONT_HERSHEY_SIMPLEX, scale, 0, max(1, int(round(scale * 1.5))), cv2.LINE_AA)
    return img


def page_origin_px(target: Target, dpi: float) -> tuple[float, float]:
    """Pixel position (u, v) of the target origin in the page image of ``to_image``."""
    _, _, ox, oy = _page(_require_planar(target))
    px_per_mm = dpi / MM_PER_INCH
    return ox * px_per_mm - 0.5, oy * px_per_mm - 0.5


def png_bytes(img: NDArray[np.uint8], dpi: float) -> bytes:
    """An 8-bit grey PNG with the resolution in its pHYs chunk (pixels per metre)."""
    h, w = img.shape

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ppm = int(round(dpi / MM_PER_INCH * 1000))
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"pHYs", struct.pack(">IIB", ppm, ppm, 1)) + chunk(b"IDAT", zlib.compress(raw, 6))
            + chunk(b"IEND", b""))


def png_dpi(data: bytes) -> float | None:
    """The resolution recorded in a PNG's pHYs chunk, in dots per inch (None if absent)."""
    pos = 8
    while pos + 8 <= len(data):
        length = struct.unpack(">I", data[pos : pos + 4])[0]
        kind = data[pos + 4 : pos + 8]
        if kind == b"pHYs":
            ppx, _ppy, unit = struct.unpack(">IIB", data[pos + 8 : pos + 17])
            return ppx * MM_PER_INCH / 1000 if unit == 1 else None
        pos += 12 + length
    return None


def page_size_mm(target: Target) -> tuple[float, float]:
    """(width, height) of the printed page in millimetres."""
    W, H, _, _ = _page(_require_planar(target))
    return W, H


def write_target(target: Target, path: str | Path, dpi: float = 300.0) -> dict[str, object]:
    """Write the printable target to ``path`` (.svg, .pdf or .png); returns a summary for the CLI."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in FORMATS:
        raise TargetPrintError(f"{p}: output must end in .svg, .pdf or .png")
    t = _require_planar(target)
    if suffix == ".svg":
        p.write_text(to_svg(t))
    elif suffix == ".pdf":
        p.write_bytes(to_pdf(t))
    else:
        p.write_bytes(png_bytes(to_image(t, dpi), dpi))
    W, H = page_size_mm(t)
    what, length = check_length(t)
    out: dict[str, object] = {"file": str(p), "format": suffix[1:], "width_mm": round(float(W), 4),
                              "height_mm": round(float(H), 4), "caption": caption(t),
                              "check": {"between": what, "length_mm": round(float(length), 4)}}
    if suffix == ".png":
        out["dpi"] = dpi
    return out
