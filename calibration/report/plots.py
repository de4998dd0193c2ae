"""The report's figures, drawn by matplotlib and embedded in the page as inline SVG.

matplotlib lays out the axes, ticks, labels and colour bars; this module adds what a calibration
report needs on top of it: a colour scale anchored to good/bad limits and fitted to the data
(:class:`Band`), and SVG a page and its tests can address (``tag``: CSS classes and ``data-``
attributes on the drawn elements; tick labels get ``class="tick"``). Text stays text in the SVG
(``svg.fonttype: none``) so it can be searched and read by a screen reader. Figure sizes are given
in CSS pixels (1 pt of the SVG = 1 px on the page).

matplotlib is imported on first use: the command line starts without it.
"""

from __future__ import annotations

import html
import io
import math
import re
import threading
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, cast
from urllib.parse import quote, unquote

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

F64 = NDArray[np.float64]
SVG_NS = "http://www.w3.org/2000/svg"
XLINK_NS = "http://www.w3.org/1999/xlink"
_SHAPES = {f"{{{SVG_NS}}}{t}" for t in ("path", "use", "rect", "text", "image", "circle", "line", "polyline",
                                        "polygon")}
_RC: dict[str, Any] = {
    "svg.fonttype": "none", "svg.hashsalt": "cellctl-report", "font.family": "sans-serif", "font.size": 9.0,
    "axes.titlesize": 10.0, "axes.titleweight": "bold", "axes.titlelocation": "left", "axes.labelsize": 9.0,
    "xtick.labelsize": 8.0, "ytick.labelsize": 8.0, "legend.fontsize": 8.0, "axes.facecolor": "#fafafa",
    "figure.dpi": 72.0, "savefig.dpi": 72.0, "image.interpolation": "nearest"}
_LOCK = threading.RLock()  # rcParams are global: one figure at a time (reports are rare, the service is threaded)

# The band colours: pale to deep green below ``good`` (fitted to the data), yellow to orange
# between ``good`` and ``bad`` (fixed), red to dark red above ``bad`` (fitted, saturating).
_GREEN = (np.array([0.651, 0.859, 0.627]), np.array([0.106, 0.471, 0.216]))
_AMBER = (np.array([0.996, 0.878, 0.545]), np.array([0.957, 0.427, 0.263]))
_RED = (np.array([0.843, 0.188, 0.153]), np.array([0.404, 0.0, 0.122]))
_GREY = np.array([0.75, 0.75, 0.75])


@dataclass(frozen=True)
class Band:
    """A colour scale for a figure of merit where smaller is better, in ``unit``.

    Anchored: a value at or below ``good`` is green, between ``good`` and ``bad`` yellow to
    orange, above ``bad`` red, whatever the data, so a good and a bad calibration look different.
    Fitted: within green and within red the shade spans the data shown (``data``), so differences
    among good values stay visible; the colour bar runs from 0 to the larger of ``bad`` and the
    data's largest value (colours saturate there).
    """

    good: float
    bad: float
    unit: str
    good_label: str = "good"
    bad_label: str = "bad"

    def __post_init__(self) -> None:
        if not (0 < self.good < self.bad and math.isfinite(self.bad)):
            raise ValueError(f"a band needs 0 < good < bad, got {self.good} and {self.bad}")

    def top(self, data: ArrayLike) -> float:
        """The colour bar's upper end for ``data``."""
        d = _finite(data)
        return max(self.bad, float(d.max()) if d.size else 0.0)

    def rgb(self, values: ArrayLike, data: ArrayLike) -> F64:
        """(N, 3) colours in [0, 1] of ``values`` on the scale fitted to ``data`` (NaN: grey)."""
        v = np.atleast_1d(np.asarray(values, dtype=np.float64))
        d = _finite(data)
        g0 = min(float(d.min()), self.good) if d.size else 0.0
        g1 = min(float(d.max()), self.good) if d.size else self.good
        r1 = self.top(d)
        out = np.tile(_GREY, (len(v), 1))
        ok = np.isfinite(v)
        for mask, (c0, c1), lo, hi in ((ok & (v <= self.good), _GREEN, g0, g1),
                                       (ok & (v > self.good) & (v <= self.bad), _AMBER, self.good, self.bad),
                                       (ok & (v > self.bad), _RED, self.bad, r1)):
            t = np.clip((v[mask] - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(int(mask.sum()), 0.5)
            out[mask] = c0 + t[:, None] * (c1 - c0)
        return out

    def hex(self, value: float, data: ArrayLike) -> str:
        r, g, b = (int(round(255 * c)) for c in self.rgb([value], data)[0])
        return f"#{r:02x}{g:02x}{b:02x}"


def _finite(x: ArrayLike) -> F64:
    a = np.asarray(x, dtype=np.float64).ravel()
    return a[np.isfinite(a)]


@contextmanager
def canvas(width_px: float, height_px: float, layout: Literal["constrained"] | None = "constrained",
           rc: dict[str, Any] | None = None) -> Iterator[Figure]:
    """A new figure of ``width_px`` x ``height_px`` CSS pixels with the report's style; draw and call
    :func:`svg` inside the block. ``layout=None``: the caller places the axes (:func:`fixed_axes`),
    which saves the layout's extra drawing pass on figures full of text. ``rc``: settings on top of
    the report's (a PDF's font embedding)."""
    import matplotlib
    from matplotlib.figure import Figure

    with _LOCK, matplotlib.rc_context(cast(Any, {**_RC, **(rc or {})})):
        yield Figure(figsize=(width_px / 72.0, height_px / 72.0), layout=layout)


def fixed_axes(fig: Figure, left_px: float = 58, right_px: float = 12, top_px: float = 24, bottom_px: float = 40,
               colourbar_px: float = 0) -> tuple[Axes, Axes | None]:
    """Axes placed by margins in px (and a colour bar's axes ``colourbar_px`` wide at the right)."""
    w, h = (float(x) * 72.0 for x in fig.get_size_inches())
    right = right_px + (colourbar_px + 34 if colourbar_px else 0)  # the gap holds the band's labels
    ax = fig.add_axes((left_px / w, bottom_px / h, 1 - (left_px + right) / w, 1 - (top_px + bottom_px) / h))
    cax = None
    if colourbar_px:
        cax = fig.add_axes((1 - (right_px + colourbar_px) / w, bottom_px / h, 14 / w, 1 - (top_px + bottom_px) / h))
    return ax, cax


def tag(artist: Any, classes: str, **data: object) -> None:
    """Give ``artist``'s SVG group (and the shapes in it) CSS ``classes`` and ``data-*`` attributes."""
    artist.set_gid("@" + "|".join([quote(classes)] + [f"{k}={quote(str(v))}" for k, v in data.items()]))


def svg(fig: Figure, css_class: str, label: str, images: dict[str, bytes] | None = None) -> str:
    """The figure as an inline ``<svg class="css_class">`` (``label``: its accessible name).

    ``images``: JPEG data by the ``photo`` tag's ``src`` attribute, put in place of matplotlib's
    re-encoded PNG (the page keeps the small JPEG it was given)."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    ET.register_namespace("", SVG_NS)
    ET.register_namespace("xlink", XLINK_NS)
    root = ET.fromstring(buf.getvalue())
    for meta in root.findall(f"{{{SVG_NS}}}metadata"):
        root.remove(meta)
    tagged = []
    for el in root.iter():
        gid = el.get("id", "")
        if gid.startswith(("xtick_", "ytick_")):
            for t in el.iter(f"{{{SVG_NS}}}text"):
                t.set("class", "tick")
        elif gid.startswith("@"):
            tagged.append(el)
    for el in reversed(tagged):  # inner tags first: an outer tag does not overwrite them
        _apply_tag(el, el.attrib.pop("id")[1:], images or {})
    w, h = (float(re.sub(r"[a-z]+$", "", root.get(k, "0"))) for k in ("width", "height"))
    attrib = {"class": css_class, "role": "img", "aria-label": label, "width": f"{w:g}", "height": f"{h:g}",
              "viewBox": root.get("viewBox", f"0 0 {w:g} {h:g}"), "xmlns": SVG_NS, "xmlns:xlink": XLINK_NS}
    body = re.sub(r"^<svg[^>]*>", "", ET.tostring(root, encoding="unicode"), count=1)
    return "<svg " + " ".join(f'{k}="{html.escape(v, quote=True)}"' for k, v in attrib.items()) + ">" + body


def _apply_tag(el: ET.Element, spec: str, images: dict[str, bytes]) -> None:
    import base64

    classes, *pairs = spec.split("|")
    data = dict(p.split("=", 1) for p in pairs)
    el.set("class", unquote(classes))
    for k, v in data.items():
        el.set(f"data-{k}", unquote(v))
    for child in el.iter():  # the element itself too: an image carries its tag as its own id
        if child is not el and child.tag in _SHAPES and "class" not in child.attrib:
            child.set("class", unquote(classes))
        if child.tag == f"{{{SVG_NS}}}image" and unquote(data.get("src", "")) in images:
            jpeg = base64.b64encode(images[unquote(data["src"])]).decode()
            child.set(f"{{{XLINK_NS}}}href", f"data:image/jpeg;base64,{jpeg}")
            child.set("preserveAspectRatio", "none")
            if child.get("transform", "").startswith("scale(1 -1)"):
                # matplotlib stores its PNG rows bottom-up and flips them back; the JPEG is top-down:
                # the same box, [y, y + height] once flipped, is [-y, -y + height] unflipped
                child.set("y", f"{-float(child.get('y', '0')):g}")
                del child.attrib["transform"]


def colourbar(fig: Figure, ax: Axes, band: Band, data: ArrayLike, cax: Axes | None = None) -> None:
    """A colour bar of ``band`` beside ``ax`` (or in ``cax``) from 0 to :meth:`Band.top`, its limits
    marked and named."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, Normalize

    top = band.top(data)
    cmap = ListedColormap(band.rgb(np.linspace(0.0, top, 256), data))
    mappable = ScalarMappable(Normalize(0.0, top), cmap)
    cb = fig.colorbar(mappable, cax=cax) if cax is not None else fig.colorbar(mappable, ax=ax, fraction=0.05,
                                                                               pad=0.02)
    tag(cb.outline, "colourbar")
    cb.set_label(band.unit)
    for value, text in ((band.good, band.good_label), (band.bad, band.bad_label)):
        cb.ax.axhline(value, color="#000", lw=1.5)
        if text:
            cb.ax.text(-0.15, value, text, transform=cb.ax.get_yaxis_transform(), ha="right", va="center",
                       fontsize=7)
    tag(cb.ax, "colourbar-axis", top=f"{top:g}")


def band_rules(ax: Axes, band: Band, horizontal: bool = True) -> None:
    """The band's limits as rules across ``ax`` (dashed green at good, dashed red at bad), shaded between."""
    span, rule = (ax.axhspan, ax.axhline) if horizontal else (ax.axvspan, ax.axvline)
    span(band.good, band.bad, color="#fee08b", alpha=0.35, lw=0, zorder=0)
    rule(band.good, color="#1b7837", lw=1.0, ls="--", label=f"{band.good_label} {band.good:g} {band.unit}")
    rule(band.bad, color="#d73027", lw=1.0, ls="--", label=f"{band.bad_label} {band.bad:g} {band.unit}")


def named_bars(ax: Axes, names: Sequence[str], values: Sequence[float], band: Band, classes: str = "bar",
               note: bool = True) -> None:
    """One bar per name, coloured on ``band``; the names on the x axis; each bar tagged with its
    ``data-name`` and ``data-value`` (the number plotted). ``note``: say so when every bar is below
    the good limit (the axis, fitted to the bars, then leaves the band out)."""
    v = np.asarray([x if x is not None and math.isfinite(x) else math.nan for x in values], dtype=np.float64)
    colours = band.rgb(v, v)
    bars = ax.bar(np.arange(len(v)), np.nan_to_num(v), color=colours, width=0.8, zorder=2)
    for name, value, bar in zip(names, v, bars, strict=True):
        tag(bar, classes, name=name, value=f"{value:.6g}")
    ax.set_xticks(np.arange(len(v)), [short_name(n) for n in names], rotation=90,
                  fontsize=7.0 if len(v) <= 60 else 5.5)
    ax.set_xlim(-0.6, max(len(v), 1) - 0.4)
    top = float(np.nanmax(v)) if np.any(np.isfinite(v)) else 1.0
    ax.set_ylim(0.0, max(top, 1e-9) * 1.15)
    band_rules(ax, band)
    if note and top < band.good:
        ax.text(0.99, 0.97, f"all below the {band.good_label} limit {band.good:g} {band.unit}",
                transform=ax.transAxes, ha="right", va="top", fontsize=7.5, color="#1b7837")


def bars_width_px(n: int) -> float:
    """A per-item bar chart's width: wide enough for ``n`` names on its axis, within the page."""
    return float(min(max(560, 12 * n + 120), 960))


def short_name(name: str, most: int = 28) -> str:
    """``name`` shortened in the middle to ``most`` characters (the full name is in ``data-name``)."""
    return name if len(name) <= most else name[: most // 2 - 1] + "…" + name[-(most // 2 - 1):]


def segments(ax: Axes, start: F64, end: F64, colour: str, width: float, classes: str) -> None:
    """Line segments from ``start`` to ``end`` (both (N, 2), data units) as one SVG path."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path

    n = len(start)
    if n == 0:
        return
    verts = np.empty((2 * n, 2))
    verts[0::2], verts[1::2] = start, end
    codes = np.tile([Path.MOVETO, Path.LINETO], n).astype(np.uint8)
    patch = PathPatch(Path(verts, codes), fill=False, edgecolor=colour, lw=width, capstyle="round")
    ax.add_patch(patch)
    tag(patch, classes, n=n)


def cell_outline(ax: Axes, mask: NDArray[np.bool_], extent: tuple[float, float, float, float], colour: str,
                 width: float, classes: str = "contour") -> None:
    """The outline of the cells where ``mask`` (ny, nx) is true over ``extent`` = (x0, x1, y0, y1)."""
    ny, nx = mask.shape
    x0, x1, y0, y1 = extent
    cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
    m = np.pad(mask.astype(bool), 1)
    a: list[tuple[float, float]] = []
    b: list[tuple[float, float]] = []
    for iy in range(ny + 1):
        for ix in range(nx):
            if m[iy, ix + 1] != m[iy + 1, ix + 1]:
                a.append((x0 + ix * cw, y0 + iy * ch))
                b.append((x0 + (ix + 1) * cw, y0 + iy * ch))
    for iy in range(ny):
        for ix in range(nx + 1):
            if m[iy + 1, ix] != m[iy + 1, ix + 1]:
                a.append((x0 + ix * cw, y0 + iy * ch))
                b.append((x0 + ix * cw, y0 + (iy + 1) * ch))
    segments(ax, np.array(a).reshape(-1, 2), np.array(b).reshape(-1, 2), colour, width, classes)


def image_axes(ax: Axes, size: tuple[int, int], title: str = "", ticks: bool = True) -> None:
    """``ax`` as an image of ``size`` = (width, height) px: pixel centres at integers, v down."""
    w, h = size
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    if title:
        ax.set_title(title)
    if ticks:
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    else:
        ax.set_xticks([])
        ax.set_yticks([])


def warm_up() -> None:
    """Import matplotlib and draw one small figure as SVG: what a process's first report would pay
    (the import, the SVG backend and, on a fresh machine, matplotlib's font cache)."""
    with canvas(120, 80, layout=None) as fig:
        ax, _ = fixed_axes(fig)
        ax.plot([0.0, 1.0], [0.0, 1.0])
        svg(fig, "warm-up", "warm-up")
