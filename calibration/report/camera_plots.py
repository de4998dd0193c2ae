"""The camera report's figures (matplotlib, inline SVG): residuals in the image and against the
radius, per-view RMS by view name, the projection uncertainty, coverage, distortion, thumbnails.

Colours of residuals and uncertainties follow :class:`~calibration.report.plots.Band`: anchored
to fixed limits in px (so a good and a bad calibration look different), shaded over the data.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

from calibration.intrinsics import POINT_OUTLIER_SIGMAS, VIEW_OUTLIER_FACTOR, cell_grid
from calibration.report import plots as pl
from calibration.report.camera import F64, GRID_NX, MAX_THUMBNAILS, MAX_VECTORS, CameraReport, ViewData
from calibration.report.page import esc, fmt
from calibration.verdict import MAX_PROJECTION_RMS_PX

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

RESIDUAL_BAND = pl.Band(0.3, 1.0, "px")
"""Reprojection residuals and per-view RMS: up to 0.3 px is what a sharp target and a fitting lens
model give (good detectors reach 0.03-0.1 px, docs/field-notes.md); from 1 px on a view or a
point is bad (blur, a misdetection, a model that does not fit)."""
UNCERTAINTY_BAND = pl.Band(MAX_PROJECTION_RMS_PX, 2 * MAX_PROJECTION_RMS_PX, "px", "limit", "")
"""Projection uncertainty: the verdict's limit, and twice it."""
RADIUS_BINS = 12
WIDTH_PX = 560


@contextmanager
def _image_canvas(rep: CameraReport, colourbar: bool = False) -> Iterator[tuple[Figure, Axes, Axes | None]]:
    """A figure with one image axes (and a colour bar's axes), its height fitted to the image's shape,
    the axes placed by fixed margins (no layout pass: these figures carry many labels)."""
    w, h = rep.camera.size
    cb_px = 52.0 if colourbar else 0.0
    axes_w = WIDTH_PX - 58 - 12 - (cb_px + 34 if colourbar else 0)
    with pl.canvas(WIDTH_PX, axes_w * h / w + 24 + 40, layout=None) as fig:
        ax, cax = pl.fixed_axes(fig, colourbar_px=cb_px)
        yield fig, ax, cax


def _extent(rep: CameraReport) -> tuple[float, float, float, float]:
    w, h = rep.camera.size
    return (-0.5, w - 0.5, -0.5, h - 0.5)


def _cells(fig: Figure, ax: Axes, cax: Axes | None, rep: CameraReport, grid: F64, band: pl.Band,
           digits: int = 2) -> None:
    """``grid`` (ny, nx) as coloured cells over the image with their values, and the band's colour bar."""
    ny, nx = grid.shape
    rgb = band.rgb(grid.ravel(), grid).reshape(ny, nx, 3)
    x0, x1, y0, y1 = _extent(rep)
    ax.imshow(rgb, extent=(x0, x1, y1, y0), alpha=0.9, zorder=1)
    cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
    if nx <= 24 and WIDTH_PX / nx >= 22:
        for iy in range(ny):
            for ix in range(nx):
                if math.isfinite(grid[iy, ix]):
                    ax.text(x0 + (ix + 0.5) * cw, y0 + (iy + 0.5) * ch, f"{grid[iy, ix]:.{digits}f}", fontsize=6.5,
                            ha="center", va="center", zorder=3, in_layout=False)
    pl.colourbar(fig, ax, band, grid, cax)


def residual_figure(rep: CameraReport) -> str:
    """Residual vectors in the image (binned per cell above :data:`MAX_VECTORS` points)."""
    uv, r = rep.residuals()
    sigma = float(rep.result.get("residual_sigma_px") or 0.0) or (float(np.std(r)) if len(r) else 0.1)
    mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
    with _image_canvas(rep, colourbar=len(r) > MAX_VECTORS) as (fig, ax, cax):
        if len(r) <= MAX_VECTORS:
            title = f"Residual vectors ({len(r)} points)"
            pl.image_axes(ax, rep.camera.size, title)
            ref = float(np.percentile(mags, 95)) if len(mags) else 1.0
            px_per_unit = ax.get_position().width * WIDTH_PX / rep.camera.size[0]
            gain = 20.0 / max(ref, 1e-9) / px_per_unit
            bad = mags > POINT_OUTLIER_SIGMAS * sigma
            pl.segments(ax, uv[~bad], uv[~bad] + gain * r[~bad], "#06c", 0.8, "residual-vectors")
            pl.segments(ax, uv[bad], uv[bad] + gain * r[bad], "#c00", 1.4, "outlier-vectors")
            note = (f"each line runs from a detected point to the model's projection of it, magnified {fmt(gain)}x "
                    f"(about 20 screen px = {fmt(ref)} px, the 95th percentile); red: outlier points "
                    f"(> {POINT_OUTLIER_SIGMAS:g} sigma = {fmt(POINT_OUTLIER_SIGMAS * sigma)} px)")
        else:
            title = f"Residual RMS per cell ({len(r)} points, binned)"
            pl.image_axes(ax, rep.camera.size, title)
            rms, mean = _binned(rep, uv, r)
            _cells(fig, ax, cax, rep, rms, RESIDUAL_BAND)
            centres, nx, _ = cell_grid(rep.camera.size, GRID_NX)
            mv = mean.reshape(-1, 2)
            top = float(np.nanmax(np.linalg.norm(mv, axis=1))) if len(mv) else 0.0
            gain = (rep.camera.size[0] / nx * 0.45) / max(top, 1e-9)
            q = ax.quiver(centres[:, 0], centres[:, 1], mv[:, 0] * gain, mv[:, 1] * gain, angles="xy",
                          scale_units="xy", scale=1.0, color="#000", width=0.004, zorder=4)
            pl.tag(q, "mean-arrows", n=len(mv))
            note = (f"colour: RMS residual per cell ({RESIDUAL_BAND.good:g} px good, {RESIDUAL_BAND.bad:g} px bad); "
                    f"arrows: mean residual per cell, largest {fmt(top)} px")
        out = pl.svg(fig, "plot residuals", title)
    return out + f"<p class='note'>{esc(note)}</p>"


def _binned(rep: CameraReport, uv: F64, r: F64) -> tuple[F64, F64]:
    """Per image cell: RMS residual length (NaN where empty) and mean residual vector."""
    _, nx, ny = cell_grid(rep.camera.size, GRID_NX)
    w, h = rep.camera.size
    ix = np.clip(((uv[:, 0] + 0.5) / w * nx).astype(int), 0, nx - 1)
    iy = np.clip(((uv[:, 1] + 0.5) / h * ny).astype(int), 0, ny - 1)
    rms = np.full((ny, nx), np.nan)
    mean = np.zeros((ny, nx, 2))
    for j in range(ny):
        for i in range(nx):
            sel = (ix == i) & (iy == j)
            if np.any(sel):
                rms[j, i] = float(np.sqrt(np.mean(np.sum(r[sel] ** 2, axis=1))))
                mean[j, i] = r[sel].mean(axis=0)
    return rms, mean


def residual_histogram(rep: CameraReport) -> str:
    _, r = rep.residuals()
    mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
    sigma = float(rep.result.get("residual_sigma_px") or 0.0)
    limit = POINT_OUTLIER_SIGMAS * sigma if sigma else None
    with pl.canvas(WIDTH_PX, 240) as fig:
        ax = fig.subplots()
        hi = max(float(np.percentile(mags, 99.5)) if len(mags) else 1.0, limit or 0.0, 1e-9) * 1.05
        ax.hist(np.clip(mags, 0, hi), bins=40, range=(0.0, hi), color="#4a7fb5")
        if limit is not None:
            ax.axvline(limit, color="#c00", lw=1.5, ls="--", label=f"outlier limit {fmt(limit)} px")
            ax.legend(loc="upper right")
        ax.set(title="Residual lengths", xlabel="residual length (px)", ylabel="count")
        return pl.svg(fig, "plot histogram", "Residual lengths")


def radius_figure(rep: CameraReport) -> str:
    """Residuals against the distance from the principal point: a lens model that does not fit shows
    as a trend with the radius (the signed radial part: + outward, - inward)."""
    uv, r = rep.residuals()
    cx, cy = rep.camera.K[0, 2], rep.camera.K[1, 2]
    d = uv - np.array([cx, cy])
    radius = np.linalg.norm(d, axis=1)
    mags = np.linalg.norm(r, axis=1)
    radial = np.einsum("ij,ij->i", r, d) / np.maximum(radius, 1e-9)
    w, h = rep.camera.size
    r_max = float(np.hypot(max(cx, w - cx), max(cy, h - cy)))
    edges = np.linspace(0.0, r_max, RADIUS_BINS + 1)
    k = np.clip(np.digitize(radius, edges) - 1, 0, RADIUS_BINS - 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    rms = np.array([np.sqrt(np.mean(mags[k == i] ** 2)) if np.any(k == i) else np.nan for i in range(RADIUS_BINS)])
    mean_radial = np.array([np.mean(radial[k == i]) if np.any(k == i) else np.nan for i in range(RADIUS_BINS)])
    with pl.canvas(WIDTH_PX, 280) as fig:
        ax = fig.subplots()
        if len(mags) <= MAX_VECTORS:
            dots = ax.scatter(radius, mags, s=3, color="#9ab", lw=0, label="point residual length", zorder=2)
            pl.tag(dots, "radius-points", n=len(mags))
        line = ax.plot(centres, rms, "o-", color="#24527a", ms=3, label="RMS per radius bin", zorder=3)[0]
        pl.tag(line, "radius-rms", values=" ".join(f"{x:.4g}" for x in rms))
        ax.plot(centres, mean_radial, "s--", color="#80c", ms=3, label="mean radial part (+ outward)", zorder=3)
        ax.axhline(0.0, color="#555", lw=0.6)
        pl.band_rules(ax, RESIDUAL_BAND)
        top = max(float(np.nanmax(mags)) if len(mags) else 0.0, RESIDUAL_BAND.good) * 1.1
        ax.set_ylim(min(0.0, float(np.nanmin(mean_radial)) * 1.2 if np.any(np.isfinite(mean_radial)) else 0.0), top)
        ax.set_xlim(0.0, r_max)
        ax.set(title="Residuals against the radius", xlabel="distance from the principal point (px)",
               ylabel="residual (px)")
        ax.legend(loc="upper left", ncols=2)
        return pl.svg(fig, "plot radius", "Residuals against the distance from the principal point")


def view_bars(rep: CameraReport) -> str:
    """RMS per used view, named on the axis, coloured on :data:`RESIDUAL_BAND`; outliers hatched."""
    used = rep.used
    vals = [float(v.rms_px) if v.rms_px is not None else math.nan for v in used]
    finite = [x for x in vals if math.isfinite(x)]
    med = float(np.median(finite)) if finite else 0.0
    with pl.canvas(pl.bars_width_px(len(used)), 330) as fig:
        ax = fig.subplots()
        pl.named_bars(ax, [v.image for v in used], vals, RESIDUAL_BAND, "bar view")
        for patch, v in zip(ax.patches, used, strict=False):
            if v.outlier:
                patch.set_hatch("///")
                patch.set_edgecolor("#000")
        ax.axhline(med, color="#090", lw=1.0, ls=":", label=f"median {fmt(med)} px")
        ax.axhline(VIEW_OUTLIER_FACTOR * med, color="#c00", lw=1.0, ls=":",
                   label=f"outlier limit {fmt(VIEW_OUTLIER_FACTOR * med)} px")
        ax.set_ylim(0.0, max(ax.get_ylim()[1], VIEW_OUTLIER_FACTOR * med * 1.1))
        ax.set(title=f"RMS per view ({len(used)} used)", ylabel="RMS (px)")
        ax.legend(loc="upper left", ncols=2, fontsize=7)
        return pl.svg(fig, "plot views", f"RMS per view ({len(used)} used)")


def coverage_figure(rep: CameraReport) -> str:
    c = rep.coverage.astype(np.float64)
    # 0 points: red (the model extrapolates there); 10 or more: green.
    t = np.minimum(c / 10.0, 1.0)[..., None]
    rgb = np.where(c[..., None] == 0, np.array([0.843, 0.188, 0.153]),
                   (1 - t) * np.array([0.996, 0.878, 0.545]) + t * np.array([0.106, 0.588, 0.255]))
    x0, x1, y0, y1 = _extent(rep)
    with _image_canvas(rep) as (fig, ax, _):
        pl.image_axes(ax, rep.camera.size, "Coverage: observed points per cell")
        ax.imshow(rgb, extent=(x0, x1, y1, y0), alpha=0.9)
        ny, nx = c.shape
        cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
        for j in range(ny):
            for i in range(nx):
                ax.text(x0 + (i + 0.5) * cw, y0 + (j + 0.5) * ch, str(int(c[j, i])), fontsize=6.5, ha="center",
                        va="center", in_layout=False)
        pl.cell_outline(ax, c > 0, _extent(rep), "#000", 2.0)
        svg = pl.svg(fig, "plot coverage", "Coverage: observed points per cell")
    return svg + ("<p class='note'>red: no points (distortion extrapolated there); green: 10 or more; black "
                  "outline: the covered region</p>")


def distortion_figure(rep: CameraReport) -> str:
    cam = rep.camera
    pts, _, _ = cell_grid(cam.size, GRID_NX)
    ideal = cam.undistort_points(pts)
    d = pts - ideal
    mag = np.linalg.norm(d, axis=1)
    ok = np.isfinite(mag)
    top = float(mag[ok].max()) if np.any(ok) else 0.0
    gain = (cam.size[0] / GRID_NX * 0.9) / max(top, 1e-9)
    with _image_canvas(rep) as (fig, ax, _):
        pl.image_axes(ax, cam.size, "Lens distortion: pinhole point to observed pixel")
        q = ax.quiver(ideal[ok, 0], ideal[ok, 1], d[ok, 0] * gain, d[ok, 1] * gain, angles="xy", scale_units="xy",
                      scale=1.0, color="#80c", width=0.003)
        pl.tag(q, "distortion-arrows", n=int(ok.sum()))
        pl.cell_outline(ax, rep.coverage > 0, _extent(rep), "#000", 1.5)
        svg = pl.svg(fig, "plot distortion", "Lens distortion")
    return svg + (f"<p class='note'>largest displacement {fmt(top)} px (arrows magnified {fmt(gain)}x); black "
                  "outline: the covered region</p>")


def uncertainty_figure(rep: CameraReport) -> str:
    band = UNCERTAINTY_BAND
    u = rep.uncertainty_map_px
    with _image_canvas(rep, colourbar=True) as (fig, ax, cax):
        pl.image_axes(ax, rep.camera.size, "Projection uncertainty (1 sigma)")
        _cells(fig, ax, cax, rep, u, band)
        pl.cell_outline(ax, np.isfinite(u) & (u <= band.good), _extent(rep), "#000", 2.0, "contour valid")
        pl.cell_outline(ax, rep.coverage > 0, _extent(rep), "#06c", 1.2, "contour covered")
        svg = pl.svg(fig, "plot uncertainty", "Projection uncertainty (1 sigma)")
    return svg + (f"<p class='note'>colour: green within the verdict's limit {fmt(band.good)} px (shaded over "
                  f"this map's values), yellow to orange up to {fmt(band.bad)} px, red beyond; black contour: the "
                  "valid region (uncertainty within the limit); blue: the covered region. Method: the intrinsics' "
                  "spread from the calibration's normal equations (view poses marginalised), scaled by the "
                  "weighted residual variance and propagated to pixels with the best camera rotation compensated; it "
                  "assumes independent point errors whose variance follows each view's detection precision (a "
                  "view-level jackknife raises it when the views disagree by more).</p>")


def _thumbnail(rep: CameraReport, v: ViewData, ref: float) -> str:
    import cv2

    w, h = rep.camera.size
    width = 170.0
    images: dict[str, bytes] = {}
    with pl.canvas(width, width * h / w, layout=None) as fig:
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        pl.image_axes(ax, rep.camera.size, ticks=False)
        if v.thumbnail:
            img = cv2.imdecode(np.frombuffer(v.thumbnail, np.uint8), cv2.IMREAD_GRAYSCALE)
            if img is not None:
                photo = ax.imshow(img, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), vmin=0, vmax=255)
                pl.tag(photo, "photo", src=v.image)
                images[v.image] = v.thumbnail
        gain = 12.0 / max(ref, 1e-9) / (width / w)
        if len(v.residuals_px) == len(v.uv):
            pl.segments(ax, v.uv, v.uv + gain * v.residuals_px, "#f60" if v.thumbnail else "#06c", 1.0, "vectors")
        else:  # a rejected view has no pose: its detected points only
            pl.tag(ax.scatter(v.uv[:, 0], v.uv[:, 1], s=1.5, color="#c00", lw=0), "points")
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        svg = pl.svg(fig, "thumb", v.image, images)
    state = (f"{fmt(v.rms_px)} px" if v.used else "rejected") + (" outlier" if v.outlier else "")
    return (f"<figure class='thumb{'' if v.used else ' rejected'}'>{svg}<figcaption>{esc(v.image)}<br>"
            f"{esc(state)}</figcaption></figure>")


def thumbnails(rep: CameraReport) -> str:
    views = [v for v in rep.views if len(v.uv)]
    if len(views) > MAX_THUMBNAILS:
        views = sorted(views, key=lambda v: -(v.rms_px or 0.0) if v.used else 1e9)[:MAX_THUMBNAILS]
        head = f"<p class='note'>the {MAX_THUMBNAILS} views with the largest RMS of {len(rep.views)}</p>"
    else:
        head = ""
    _, r_all = rep.residuals()
    ref = float(np.percentile(np.linalg.norm(r_all, axis=1), 95)) if len(r_all) else 1.0
    note = f"residuals magnified: 12 screen px = {fmt(ref)} px (95th percentile over all views)"
    return (head + f"<p class='note'>{esc(note)}</p><div class='thumbs'>"
            + "".join(_thumbnail(rep, v, ref) for v in views) + "</div>")


def rejected_table(rep: CameraReport) -> str:
    rows = [v for v in rep.views if not v.used or v.outlier]
    if not rows:
        return "<p>No view was rejected.</p>"
    body = "".join(f"<tr><td>{esc(v.image)}</td><td>{'outlier (used)' if v.used else 'rejected'}</td>"
                   f"<td>{esc(v.reason or ('RMS above ' + fmt(VIEW_OUTLIER_FACTOR) + 'x the median'))}</td></tr>"
                   for v in rows)
    return f"<table class='rejected'><tr><th>view</th><th>state</th><th>why</th></tr>{body}</table>"
