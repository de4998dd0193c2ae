"""Inline-SVG plots for the calibration reports: axes with ticks and labels, colour bars in physical
units, heat maps, vector fields, contours, histograms and bars (no external assets, no JavaScript).

Our own small plotting layer: a report must open from a file or a plant's service with nothing
else installed, and matplotlib would add a heavy dependency for a dozen simple figures.
Coordinates given to :class:`Axes` are data units; ``invert_y`` puts y = 0 at the top (images).
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
FONT = 'font-family="sans-serif"'


def esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def nice_ticks(lo: float, hi: float, n: int = 6) -> list[float]:
    """About ``n`` round tick values covering [lo, hi] (1, 2, 5 x 10^k steps)."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    out = []
    k = 0
    while first + k * step <= hi + 1e-9 * step:
        out.append(round(first + k * step, 10))
        k += 1
    return out


def tick_labels(ticks: list[float]) -> list[str]:
    """Tick values with as many decimals as their spacing needs (0, 0.25, 0.5 / 0, 500, 1000)."""
    if len(ticks) < 2:
        return [fmt(t, 4) for t in ticks]
    step = abs(ticks[1] - ticks[0])
    decimals = 0
    while decimals < 8 and abs(round(step, decimals) - step) > 1e-9 * max(step, 1e-300):
        decimals += 1
    return [f"{t:.{decimals}f}" if abs(t) < 1e6 else f"{t:.2e}" for t in ticks]


_CLIP_IDS = iter(range(1, 1 << 62))


def fmt(v: float | None, digits: int = 3) -> str:
    """A number rounded for people: ``digits`` significant figures, no exponent for usual sizes."""
    if v is None or not math.isfinite(v):
        return "–"
    if v == 0:
        return "0"
    a = abs(v)
    if 1e-3 <= a < 1e6:
        decimals = max(0, digits - 1 - math.floor(math.log10(a)))
        return f"{v:.{decimals}f}"
    return f"{v:.{digits - 1}e}"


# Good-to-bad scale: green below the limit, yellow at it, red at twice the limit and above.
_STOPS = [(0.0, (26, 150, 65)), (0.5, (255, 210, 60)), (1.0, (215, 25, 28))]


def colour(t: float) -> str:
    """Colour of ``t`` in [0, 1] on the green-yellow-red scale (NaN: grey)."""
    if t is None or not math.isfinite(t):
        return "#bbb"
    t = min(max(t, 0.0), 1.0)
    for (t0, c0), (t1, c1) in zip(_STOPS, _STOPS[1:], strict=False):
        if t <= t1:
            f = (t - t0) / (t1 - t0)
            r, g, b = (int(round(a + (b_ - a) * f)) for a, b_ in zip(c0, c1, strict=True))
            return f"rgb({r},{g},{b})"
    return "rgb(215,25,28)"


class Axes:
    """A plot area with data limits, ticks, labels and a title; elements are added in data units."""

    def __init__(self, x_range: tuple[float, float], y_range: tuple[float, float], width: int = 560,
                 height: int = 320, *, title: str = "", xlabel: str = "", ylabel: str = "",
                 invert_y: bool = False, right_margin: int = 20) -> None:
        self.x0, self.x1 = x_range
        self.y0, self.y1 = y_range
        if self.x1 <= self.x0:
            self.x1 = self.x0 + 1.0
        if self.y1 <= self.y0:
            self.y1 = self.y0 + 1.0
        self.left, self.top, self.bottom, self.right = 62, 28, 44, right_margin
        self.w, self.h = width, height
        self.title, self.xlabel, self.ylabel, self.invert_y = title, xlabel, ylabel, invert_y
        self.parts: list[str] = []

    @property
    def total_width(self) -> int:
        return self.left + self.w + self.right

    @property
    def total_height(self) -> int:
        return self.top + self.h + self.bottom

    def px(self, x: float, y: float) -> tuple[float, float]:
        fx = (x - self.x0) / (self.x1 - self.x0)
        fy = (y - self.y0) / (self.y1 - self.y0)
        return self.left + fx * self.w, self.top + (fy if self.invert_y else 1 - fy) * self.h

    def scale(self) -> float:
        """Screen pixels per data unit along x."""
        return self.w / (self.x1 - self.x0)

    def add(self, svg: str) -> None:
        self.parts.append(svg)

    def rect(self, x: float, y: float, w: float, h: float, fill: str, title: str = "", extra: str = "") -> None:
        xa, ya = self.px(x, y)
        xb, yb = self.px(x + w, y + h)
        tip = f"<title>{esc(title)}</title>" if title else ""
        self.add(f'<rect x="{min(xa, xb):.1f}" y="{min(ya, yb):.1f}" width="{abs(xb - xa):.1f}" '
                 f'height="{abs(yb - ya):.1f}" fill="{fill}" {extra}>{tip}</rect>')

    def line(self, x0: float, y0: float, x1: float, y1: float, stroke: str = "#333", width: float = 1.0,
             dash: str = "") -> None:
        a, b = self.px(x0, y0)
        c, d = self.px(x1, y1)
        da = f' stroke-dasharray="{dash}"' if dash else ""
        self.add(f'<line x1="{a:.1f}" y1="{b:.1f}" x2="{c:.1f}" y2="{d:.1f}" stroke="{stroke}" '
                 f'stroke-width="{width}"{da}/>')

    def text(self, x: float, y: float, s: str, size: int = 11, anchor: str = "start", fill: str = "#222") -> None:
        a, b = self.px(x, y)
        self.add(f'<text x="{a:.1f}" y="{b:.1f}" font-size="{size}" text-anchor="{anchor}" fill="{fill}" '
                 f'{FONT}>{esc(s)}</text>')

    def circle(self, x: float, y: float, r_px: float, fill: str, stroke: str = "none", title: str = "") -> None:
        a, b = self.px(x, y)
        tip = f"<title>{esc(title)}</title>" if title else ""
        self.add(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="{r_px:.1f}" fill="{fill}" stroke="{stroke}">{tip}</circle>')

    def vectors(self, xy: F64, d: F64, gain: float, stroke: str = "#06c", width: float = 0.8) -> None:
        """Arrows from ``xy`` along ``d * gain`` (both data units), drawn as one path."""
        segs = []
        for (x, y), (dx, dy) in zip(np.asarray(xy), np.asarray(d), strict=True):
            a, b = self.px(x, y)
            c, e = self.px(x + dx * gain, y + dy * gain)
            segs.append(f"M{a:.1f} {b:.1f}L{c:.1f} {e:.1f}")
        if segs:
            self.add(f'<path d="{"".join(segs)}" stroke="{stroke}" stroke-width="{width}" fill="none"/>')

    def heatmap(self, grid: F64, extent: tuple[float, float, float, float], vmax: float,
                unit: str, labels: bool = True, digits: int = 2) -> None:
        """Cells of ``grid`` (ny, nx) over ``extent`` = (x0, x1, y0, y1), coloured by value / vmax."""
        ny, nx = grid.shape
        x0, x1, y0, y1 = extent
        cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
        show = labels and nx <= 24 and self.w / nx >= 22
        for iy in range(ny):
            for ix in range(nx):
                v = float(grid[iy, ix])
                self.rect(x0 + ix * cw, y0 + iy * ch, cw, ch, colour(v / vmax if vmax > 0 else math.nan),
                          f"{fmt(v, digits + 1)} {unit}", 'fill-opacity="0.9"')
                if show and math.isfinite(v):
                    self.text(x0 + (ix + 0.5) * cw, y0 + (iy + 0.62) * ch, f"{v:.{digits}f}", 9, "middle")

    def boundary(self, mask: NDArray[np.bool_], extent: tuple[float, float, float, float],
                 stroke: str = "#000", width: float = 2.0) -> None:
        """The outline of the cells where ``mask`` is true (edges between true and false cells)."""
        ny, nx = mask.shape
        x0, x1, y0, y1 = extent
        cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
        m = np.pad(mask.astype(bool), 1)
        segs = []
        for iy in range(ny + 1):
            for ix in range(nx):
                if m[iy, ix + 1] != m[iy + 1, ix + 1]:
                    segs.append((x0 + ix * cw, y0 + iy * ch, x0 + (ix + 1) * cw, y0 + iy * ch))
        for iy in range(ny):
            for ix in range(nx + 1):
                if m[iy + 1, ix] != m[iy + 1, ix + 1]:
                    segs.append((x0 + ix * cw, y0 + iy * ch, x0 + ix * cw, y0 + (iy + 1) * ch))
        path = []
        for a, b, c, d in segs:
            p, q = self.px(a, b)
            r, s = self.px(c, d)
            path.append(f"M{p:.1f} {q:.1f}L{r:.1f} {s:.1f}")
        if path:
            self.add(f'<path class="contour" d="{"".join(path)}" stroke="{stroke}" stroke-width="{width}" '
                     'fill="none"/>')

    def svg(self, css_class: str = "plot", legend: str = "", ticks: bool = True) -> str:
        """The finished figure: frame, ticks, tick labels, axis labels, title, then the elements
        (clipped to the plot area)."""
        L, T, W, H = self.left, self.top, self.w, self.h
        clip = f"clip{next(_CLIP_IDS)}"
        frame = [f'<clipPath id="{clip}"><rect x="{L}" y="{T}" width="{W}" height="{H}"/></clipPath>',
                 f'<rect x="{L}" y="{T}" width="{W}" height="{H}" fill="#fafafa" stroke="none"/>']
        marks = []
        if ticks:
            xt = nice_ticks(self.x0, self.x1)
            for xv, label in zip(xt, tick_labels(xt), strict=True):
                a, _ = self.px(xv, self.y0)
                marks.append(f'<line x1="{a:.1f}" y1="{T + H}" x2="{a:.1f}" y2="{T + H + 5}" stroke="#333"/>'
                             f'<text class="tick" x="{a:.1f}" y="{T + H + 17}" font-size="10" text-anchor="middle" '
                             f'{FONT}>{esc(label)}</text>')
            yt = nice_ticks(self.y0, self.y1)
            for yv, label in zip(yt, tick_labels(yt), strict=True):
                _, b = self.px(self.x0, yv)
                marks.append(f'<line x1="{L - 5}" y1="{b:.1f}" x2="{L}" y2="{b:.1f}" stroke="#333"/>'
                             f'<text class="tick" x="{L - 7}" y="{b + 3.5:.1f}" font-size="10" text-anchor="end" '
                             f'{FONT}>{esc(label)}</text>')
        labels = [f'<text x="{L + W / 2:.0f}" y="{T + H + 36}" font-size="11" text-anchor="middle" {FONT}>'
                  f'{esc(self.xlabel)}</text>',
                  f'<text x="14" y="{T + H / 2:.0f}" font-size="11" text-anchor="middle" {FONT} '
                  f'transform="rotate(-90 14 {T + H / 2:.0f})">{esc(self.ylabel)}</text>',
                  f'<text x="{L}" y="17" font-size="13" font-weight="bold" {FONT}>{esc(self.title)}</text>'
                  ] if ticks else []
        border = f'<rect x="{L}" y="{T}" width="{W}" height="{H}" fill="none" stroke="#333"/>'
        return (f'<svg class="{css_class}" xmlns="http://www.w3.org/2000/svg" width="{self.total_width}" '
                f'height="{self.total_height}" viewBox="0 0 {self.total_width} {self.total_height}" role="img" '
                f'aria-label="{esc(self.title)}">{"".join(frame)}<g clip-path="url(#{clip})">{"".join(self.parts)}'
                f'</g>{border}{"".join(marks)}{"".join(labels)}{legend}</svg>')


def colourbar(ax: Axes, vmax: float, unit: str, limit: float | None = None, label: str = "") -> str:
    """A vertical colour bar right of ``ax`` from 0 to ``vmax`` (``unit``), the limit marked."""
    x = ax.left + ax.w + 14
    top, h = ax.top, ax.h
    steps = 40
    parts = [f'<rect class="colourbar" x="{x}" y="{top}" width="14" height="{h}" fill="none" stroke="#333"/>']
    for k in range(steps):
        t = (k + 0.5) / steps
        y = top + h - (k + 1) * h / steps
        parts.append(f'<rect x="{x}" y="{y:.1f}" width="14" height="{h / steps + 0.6:.1f}" fill="{colour(t)}"/>')
    cticks = nice_ticks(0.0, vmax, 5)
    for v, text in zip(cticks, tick_labels(cticks), strict=True):
        y = top + h - v / vmax * h
        parts.append(f'<line x1="{x + 14}" y1="{y:.1f}" x2="{x + 18}" y2="{y:.1f}" stroke="#333"/>'
                     f'<text class="tick" x="{x + 20}" y="{y + 3.5:.1f}" font-size="10" {FONT}>{esc(text)}</text>')
    if limit is not None and 0 < limit <= vmax:
        y = top + h - limit / vmax * h
        parts.append(f'<line x1="{x - 3}" y1="{y:.1f}" x2="{x + 17}" y2="{y:.1f}" stroke="#000" stroke-width="2"/>'
                     f'<text x="{x - 4}" y="{y - 3:.1f}" font-size="9" text-anchor="end" {FONT}>limit</text>')
    parts.append(f'<text x="{x + 7}" y="{top - 8}" font-size="10" text-anchor="middle" {FONT}>'
                 f'{esc(label or unit)}</text>')
    return "".join(parts)


def histogram(values: Sequence[float] | F64, unit: str, title: str, xlabel: str, bins: int = 40,
              limit: float | None = None, width: int = 560) -> str:
    """A histogram of ``values`` (counts), the optional ``limit`` drawn as a dashed line."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    top_v = float(np.percentile(v, 99.5)) if v.size else 1.0
    hi = max(top_v, limit or 0.0, 1e-9) * 1.05
    counts, edges = np.histogram(np.clip(v, 0, hi), bins=bins, range=(0.0, hi))
    ax = Axes((0.0, hi), (0.0, max(float(counts.max()) if counts.size else 1.0, 1.0) * 1.1), width, 220,
              title=title, xlabel=xlabel, ylabel="count")
    for c, a, b in zip(counts, edges[:-1], edges[1:], strict=True):
        if c:
            ax.rect(a, 0, b - a, float(c), "#4a7fb5", f"{fmt(a)}–{fmt(b)} {unit}: {int(c)}")
    if limit is not None:
        ax.line(limit, 0, limit, ax.y1, "#c00", 1.5, "5 3")
    return ax.svg("plot histogram")


def bars(labels: Sequence[str], values: Sequence[float], unit: str, title: str, ylabel: str,
         colours: Sequence[str] | None = None, lines: Sequence[tuple[float, str, str]] = (),
         width: int = 560, second: Sequence[float] | None = None, second_label: str = "") -> str:
    """One bar per label (hover shows label and value); ``lines``: (value, colour, legend) rules;
    ``second``: a second value per label drawn as a marker (e.g. held-out prediction)."""
    vals = np.asarray([v if v is not None and math.isfinite(v) else 0.0 for v in values], dtype=np.float64)
    extra = [x for x in (second or []) if x is not None and math.isfinite(x)]
    top = max([float(vals.max()) if vals.size else 0.0, *extra, *[ln[0] for ln in lines], 1e-9]) * 1.12
    n = max(len(vals), 1)
    ax = Axes((0.0, float(n)), (0.0, top), width, 220, title=title, xlabel=f"{n} items (hover for names)",
              ylabel=ylabel)
    for k, (lab, v) in enumerate(zip(labels, vals, strict=True)):
        col = colours[k] if colours else "#4a7fb5"
        ax.rect(k + 0.1, 0, 0.8, float(v), col, f"{lab}: {fmt(float(v))} {unit}")
        if second is not None and second[k] is not None and math.isfinite(second[k]):
            a, b = ax.px(k + 0.5, float(second[k]))
            ax.add(f'<path d="M{a - 4:.1f} {b:.1f}L{a + 4:.1f} {b:.1f}" stroke="#000" stroke-width="2.5">'
                   f"<title>{esc(lab)}: {esc(second_label)} {esc(fmt(float(second[k])))} {esc(unit)}</title></path>")
    legend_y = ax.top + 12
    for value, col, text in lines:
        ax.line(0, value, n, value, col, 1.2, "5 3")
        ax.add(f'<text x="{ax.left + ax.w - 4}" y="{ax.px(0, value)[1] - 3:.1f}" font-size="10" text-anchor="end" '
               f'fill="{col}" {FONT}>{esc(text)}</text>')
        legend_y += 12
    return ax.svg("plot bars")
