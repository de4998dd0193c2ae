"""The camera (intrinsics) part of the HTML report, built from ``cam.json`` and the detections.

Everything is recomputed from what is stored (the result JSON, each view's detected points and
its ``T_cam_target``), so the CLI's ``--report`` and the service's ``/calibrations/{id}/report``
are the same report. The residuals follow from the stored poses: at the solver's optimum each
view's pose is optimal for the stored intrinsics, so projecting the target through them gives the
solver's residuals. Colour scales are anchored to the verdict's limits, not to the data.
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.intrinsics import (
    POINT_OUTLIER_SIGMAS,
    VIEW_OUTLIER_FACTOR,
    cell_grid,
    coverage_counts,
    uncertainty_summary,
)
from calibration.report.svg import Axes, bars, colour, colourbar, esc, fmt, histogram
from calibration.targets import Target
from calibration.verdict import MAX_PROJECTION_RMS_PX

F64 = NDArray[np.float64]
MAX_VECTORS = 3000
"""Above this many residuals the residual plot shows per-cell RMS and mean vectors instead."""
MAX_THUMBNAILS = 48
GRID_NX = 16


@dataclass
class ViewData:
    image: str
    used: bool
    rms_px: float | None
    reason: str = ""
    outlier: bool = False
    uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    thumbnail: bytes | None = None
    """A small JPEG of the image (CLI only: the service does not keep images)."""


@dataclass
class CameraReport:
    camera: CameraModel
    result: dict[str, Any]
    views: list[ViewData]
    coverage: NDArray[np.int64]
    uncertainty_map_px: F64

    @property
    def used(self) -> list[ViewData]:
        return [v for v in self.views if v.used]

    def residuals(self) -> tuple[F64, F64]:
        used = self.used
        if not used:
            return np.zeros((0, 2)), np.zeros((0, 2))
        return np.vstack([v.uv for v in used]), np.vstack([v.residuals_px for v in used])

    def to_json(self) -> dict[str, Any]:
        """The report's figures as rounded JSON (``GET /calibrations/{id}/report?format=json``)."""
        _, r = self.residuals()
        mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
        return {
            "kind": "camera", "model": self.camera.model, "size": list(self.camera.size),
            "verdict": self.result.get("verdict"),
            "rms_px": _round(self.result.get("rms_px")),
            "views": [{"image": v.image, "used": v.used, "rms_px": _round(v.rms_px), "outlier": v.outlier,
                       **({"reason": v.reason} if v.reason else {})} for v in self.views],
            "rejected_views": [{"image": v.image, "reason": v.reason or "not used"} for v in self.views if not v.used],
            "residual_px": {"n": int(len(mags)), "rms": _round(float(np.sqrt(np.mean(mags**2))) if len(mags) else None),
                            "p95": _round(float(np.percentile(mags, 95)) if len(mags) else None)},
            "coverage_points_per_cell": self.coverage.tolist(),
            "uncertainty_map_px": [[_round(x) for x in row] for row in self.uncertainty_map_px],
            "uncertainty_limit_px": MAX_PROJECTION_RMS_PX,
        }


def _round(x: Any, digits: int = 4) -> float | None:
    if x is None or not isinstance(x, int | float) or not math.isfinite(x):
        return None
    return float(f"{x:.{digits}g}")


def build(result: dict[str, Any], detections: list[dict[str, Any]], target: Target | None,
          images: dict[str, bytes] | None = None) -> CameraReport:
    """The report of ``result`` (``cam.json``), ``detections`` (``cellctl detect`` JSON per view).

    Without a target (a camera stored without its detections) the views carry no points and the
    uncertainty map treats the whole image as covered."""
    camera = CameraModel.from_dict(result)
    pts = target.points() if target is not None else None
    lookup = {int(i): k for k, i in enumerate(pts.ids)} if pts is not None else {}
    by_image = {str(d.get("image")): d for d in detections}
    views = []
    for v in result.get("views", []):
        name = str(v.get("image"))
        vd = ViewData(name, bool(v.get("used")), v.get("rms_px"), str(v.get("reason") or ""), bool(v.get("outlier")),
                      thumbnail=(images or {}).get(name))
        det = by_image.get(name)
        T = v.get("T_cam_target")
        if det is not None and det.get("points"):
            ids = [int(p["id"]) for p in det["points"] if int(p["id"]) in lookup]
            uv = np.array([[p["u_px"], p["v_px"]] for p in det["points"] if int(p["id"]) in lookup], dtype=np.float64)
            vd.uv = uv.reshape(-1, 2)
            if T is not None and len(ids) and pts is not None:
                xyz = g.transform_points(np.asarray(T, dtype=np.float64), pts.xyz_m[[lookup[i] for i in ids]])
                vd.residuals_px = camera.project(xyz) - vd.uv  # the solver's sign: projection - observation
        views.append(vd)
    used_uv = np.vstack([v.uv for v in views if v.used and len(v.uv)]) if any(
        v.used and len(v.uv) for v in views) else np.zeros((0, 2))
    coverage = coverage_counts(camera.size, used_uv, GRID_NX)
    cov = np.asarray((result.get("parameters") or {}).get("covariance") or [], dtype=np.float64)
    if cov.size:
        fit = coverage if coverage.sum() else np.ones_like(coverage)
        _, umap = uncertainty_summary(camera, cov, fit)
    else:
        umap = np.full(coverage.shape, np.nan)
    return CameraReport(camera, result, views, coverage, umap)


# ---------------------------------------------------------------------------------------- figures


def _image_axes(rep: CameraReport, title: str, right: int = 20) -> Axes:
    w, h = rep.camera.size
    width = 560
    return Axes((-0.5, w - 0.5), (-0.5, h - 0.5), width, int(round(width * h / w)), title=title,
                xlabel="u (px)", ylabel="v (px)", invert_y=True, right_margin=right)


def _extent(rep: CameraReport) -> tuple[float, float, float, float]:
    w, h = rep.camera.size
    return (-0.5, w - 0.5, -0.5, h - 0.5)


def residual_figure(rep: CameraReport) -> str:
    uv, r = rep.residuals()
    sigma = float(rep.result.get("residual_sigma_px") or 0.0) or (float(np.std(r)) if len(r) else 0.1)
    limit = 3.0 * sigma
    if len(r) <= MAX_VECTORS:
        ax = _image_axes(rep, f"Residual vectors ({len(r)} points)")
        mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
        ref = float(np.percentile(mags, 95)) if len(mags) else 1.0
        gain = 20.0 / max(ref, 1e-9) / ax.scale()
        ax.vectors(uv, r, gain)
        bad = mags > POINT_OUTLIER_SIGMAS * sigma
        if np.any(bad):
            ax.vectors(uv[bad], r[bad], gain, "#c00", 1.4)
        note = (f"each arrow runs from a detected point to the model's projection of it, magnified {fmt(gain)}x: "
                f"20 screen px = {fmt(ref)} px (95th percentile); red: outlier "
                f"points (> {POINT_OUTLIER_SIGMAS:g} sigma = {fmt(POINT_OUTLIER_SIGMAS * sigma)} px)")
        return ax.svg("plot residuals") + f"<p class='note'>{esc(note)}</p>"
    # Large sets: RMS per cell and the mean vector per cell (a systematic pattern shows as arrows).
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
    ax = _image_axes(rep, f"Residual RMS per cell ({len(r)} points, binned)", right=80)
    ax.heatmap(rms, _extent(rep), 2 * limit, "px")
    centres, _, _ = cell_grid(rep.camera.size, GRID_NX)
    mv = mean.reshape(-1, 2)
    top = float(np.nanmax(np.linalg.norm(mv, axis=1))) if len(mv) else 0.0
    gain = (w / nx * 0.45) / max(top, 1e-9)
    ax.vectors(centres, mv, gain, "#000", 1.3)
    note = (f"colour: RMS residual per cell, limit {fmt(limit)} px = 3 sigma of the point residuals; arrows: "
            f"mean residual per cell, largest {fmt(top)} px")
    return ax.svg("plot residuals", colourbar(ax, 2 * limit, "px", limit)) + f"<p class='note'>{esc(note)}</p>"


def residual_histogram(rep: CameraReport) -> str:
    _, r = rep.residuals()
    mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
    sigma = float(rep.result.get("residual_sigma_px") or 0.0)
    limit = POINT_OUTLIER_SIGMAS * sigma if sigma else None
    return histogram(mags, "px", "Residual lengths", "residual length (px); dashed: outlier limit", limit=limit)


def view_bars(rep: CameraReport) -> str:
    used = rep.used
    vals = [float(v.rms_px) if v.rms_px is not None else math.nan for v in used]
    med = float(np.median([x for x in vals if math.isfinite(x)])) if vals else 0.0
    cols = ["#c00" if v.outlier else "#4a7fb5" for v in used]
    return bars([v.image for v in used], vals, "px", f"RMS per view ({len(used)} used)", "RMS (px)", cols,
                [(med, "#090", f"median {fmt(med)} px"),
                 (VIEW_OUTLIER_FACTOR * med, "#c00", f"outlier limit {fmt(VIEW_OUTLIER_FACTOR * med)} px")])


def coverage_figure(rep: CameraReport) -> str:
    ax = _image_axes(rep, "Coverage: observed points per cell")
    c = rep.coverage.astype(np.float64)
    # 0 points: red (the model extrapolates there); 10 or more: green.
    t = np.where(c == 0, 1.0, 0.5 * (1 - np.minimum(c / 10.0, 1.0)))
    ny, nx = c.shape
    x0, x1, y0, y1 = _extent(rep)
    cw, ch = (x1 - x0) / nx, (y1 - y0) / ny
    for j in range(ny):
        for i in range(nx):
            ax.rect(x0 + i * cw, y0 + j * ch, cw, ch, colour(float(t[j, i])), f"{int(c[j, i])} points",
                    'fill-opacity="0.9"')
            ax.text(x0 + (i + 0.5) * cw, y0 + (j + 0.62) * ch, str(int(c[j, i])), 9, "middle")
    ax.boundary(c > 0, _extent(rep))
    return ax.svg("plot coverage") + ("<p class='note'>red: no points (distortion extrapolated there); green: 10 "
                                      "or more; black outline: the covered region</p>")


def distortion_figure(rep: CameraReport) -> str:
    cam = rep.camera
    pts, _, _ = cell_grid(cam.size, GRID_NX)
    ideal = cam.undistort_points(pts)
    d = pts - ideal
    mag = np.linalg.norm(d, axis=1)
    ok = np.isfinite(mag)
    top = float(mag[ok].max()) if np.any(ok) else 0.0
    ax = _image_axes(rep, "Lens distortion: pinhole point to observed pixel")
    w, _ = cam.size
    gain = (w / GRID_NX * 0.9) / max(top, 1e-9)
    ax.vectors(ideal[ok], d[ok], gain, "#80c", 1.2)
    ax.boundary(rep.coverage > 0, _extent(rep), "#000", 1.5)
    return ax.svg("plot distortion") + (f"<p class='note'>largest displacement {fmt(top)} px (arrows magnified "
                                        f"{fmt(gain)}x); black outline: the covered region</p>")


def uncertainty_figure(rep: CameraReport) -> str:
    limit = MAX_PROJECTION_RMS_PX
    ax = _image_axes(rep, "Projection uncertainty (1 sigma)", right=80)
    u = rep.uncertainty_map_px
    ax.heatmap(u, _extent(rep), 2 * limit, "px")
    ax.boundary(np.isfinite(u) & (u <= limit), _extent(rep), "#000", 2.0)
    ax.boundary(rep.coverage > 0, _extent(rep), "#06c", 1.2)
    return (ax.svg("plot uncertainty", colourbar(ax, 2 * limit, "px", limit))
            + f"<p class='note'>colour: 0 to {fmt(2 * limit)} px, the verdict's limit {fmt(limit)} px marked; black "
              "contour: the valid region (uncertainty within the limit); blue: the covered region</p>")


def thumbnails(rep: CameraReport) -> str:
    views = [v for v in rep.views if len(v.uv)]
    if len(views) > MAX_THUMBNAILS:
        views = sorted(views, key=lambda v: -(v.rms_px or 0.0) if v.used else 1e9)[:MAX_THUMBNAILS]
        head = f"<p class='note'>the {MAX_THUMBNAILS} views with the largest RMS of {len(rep.views)}</p>"
    else:
        head = ""
    w, h = rep.camera.size
    _, r_all = rep.residuals()
    ref = float(np.percentile(np.linalg.norm(r_all, axis=1), 95)) if len(r_all) else 1.0
    out = []
    for v in views:
        ax = Axes((-0.5, w - 0.5), (-0.5, h - 0.5), 170, int(round(170 * h / w)), title="", invert_y=True,
                  right_margin=4)
        ax.left, ax.top, ax.bottom = 4, 4, 4
        if v.thumbnail:
            a, b = ax.px(-0.5, -0.5)
            data = base64.b64encode(v.thumbnail).decode()
            ax.add(f'<image x="{a:.1f}" y="{b:.1f}" width="{ax.w}" height="{ax.h}" preserveAspectRatio="none" '
                   f'href="data:image/jpeg;base64,{data}"/>')
        gain = 12.0 / max(ref, 1e-9) / ax.scale()
        if len(v.residuals_px) == len(v.uv):
            ax.vectors(v.uv, v.residuals_px, gain, "#f60" if v.thumbnail else "#06c", 1.0)
        else:  # a rejected view has no pose: its detected points only
            for u, q in v.uv:
                ax.circle(float(u), float(q), 1.2, "#c00")
        svg = ax.svg("thumb", ticks=False)
        state = (f"{fmt(v.rms_px)} px" if v.used else "rejected") + (" outlier" if v.outlier else "")
        out.append(f"<figure class='thumb{'' if v.used else ' rejected'}'>{svg}<figcaption>{esc(v.image)}<br>"
                   f"{esc(state)}</figcaption></figure>")
    note = f"residuals magnified: 12 screen px = {fmt(ref)} px (95th percentile over all views)"
    return head + f"<p class='note'>{esc(note)}</p><div class='thumbs'>{''.join(out)}</div>"


def rejected_table(rep: CameraReport) -> str:
    rows = [v for v in rep.views if not v.used or v.outlier]
    if not rows:
        return "<p>No view was rejected.</p>"
    body = "".join(f"<tr><td>{esc(v.image)}</td><td>{'outlier (used)' if v.used else 'rejected'}</td>"
                   f"<td>{esc(v.reason or ('RMS above ' + fmt(VIEW_OUTLIER_FACTOR) + 'x the median'))}</td></tr>"
                   for v in rows)
    return f"<table class='rejected'><tr><th>view</th><th>state</th><th>why</th></tr>{body}</table>"
