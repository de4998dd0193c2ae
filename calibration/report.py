"""A self-contained HTML report of an intrinsics calibration (inline SVG, no external files).

Sections: verdict and numbers, residual vectors over the image, per-view RMS bars, coverage heat
map, lens distortion field and the projection uncertainty map. Meant to be read at a glance:
green is good, red needs action.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.intrinsics import IntrinsicsResult, _grid

W_SVG = 640


def _colour(x: float) -> str:
    """0 -> green, 1 -> red (clamped)."""
    x = float(np.clip(x, 0.0, 1.0)) if np.isfinite(x) else 1.0
    r, g = int(40 + 200 * x), int(180 - 140 * x)
    return f"rgb({r},{g},60)"


def _frame(w: int, h: int, body: str, note: str = "") -> str:
    s = W_SVG / w
    hh = int(round(h * s))
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{W_SVG}" height="{hh + 18}" '
            f'viewBox="0 0 {W_SVG} {hh + 18}"><rect x="0" y="0" width="{W_SVG}" height="{hh}" fill="#f4f4f4" '
            f'stroke="#333"/>{body}<text x="2" y="{hh + 14}" font-size="12">{html.escape(note)}</text></svg>')


def residual_svg(res: IntrinsicsResult) -> str:
    w, h = res.camera.size
    s = W_SVG / w
    used = [v for v in res.views if v.used]
    mags = np.concatenate([np.linalg.norm(v.residuals_px, axis=1) for v in used]) if used else np.zeros(1)
    ref = float(np.percentile(mags, 95)) if mags.size else 1.0
    gain = 15.0 / max(ref, 1e-9)
    parts = []
    for v in used:
        for (u, q), (du, dv) in zip(v.uv, v.residuals_px, strict=True):
            x, y = u * s, q * s
            parts.append(f'<line x1="{x:.1f}" y1="{y:.1f}" x2="{x + du * gain:.1f}" y2="{y + dv * gain:.1f}" '
                         f'stroke="{"#c00" if np.hypot(du, dv) > 3 * ref else "#06c"}" stroke-width="1"/>')
    return _frame(w, h, "".join(parts), f"residuals x{gain:.0f} (95th percentile {ref:.3f} px = 15 display px)")


def view_bars_svg(res: IntrinsicsResult) -> str:
    views = res.views
    n = max(len(views), 1)
    bw = max(4.0, min(30.0, (W_SVG - 60) / n))
    rms = np.array([v.rms_px if v.used and np.isfinite(v.rms_px) else 0.0 for v in views])
    top = max(float(rms.max()) if rms.size else 1.0, 1e-6) * 1.1
    med = float(np.median(rms[rms > 0])) if np.any(rms > 0) else 0.0
    H = 180
    parts = []
    for k, v in enumerate(views):
        x = 50 + k * bw
        if not v.used:
            parts.append(f'<text x="{x + 1:.1f}" y="{H - 4}" font-size="9" fill="#999">x</text>')
            continue
        hgt = rms[k] / top * (H - 20)
        col = "#c00" if v.outlier else "#06c"
        parts.append(f'<rect x="{x:.1f}" y="{H - hgt:.1f}" width="{bw * 0.8:.1f}" height="{hgt:.1f}" fill="{col}">'
                     f"<title>{html.escape(v.image)}: {v.rms_px:.3f} px</title></rect>")
    parts.append(f'<text x="2" y="12" font-size="11">{top:.3g} px</text>')
    if med:
        y = H - med / top * (H - 20)
        parts.append(f'<line x1="45" x2="{W_SVG}" y1="{y:.1f}" y2="{y:.1f}" stroke="#090" stroke-dasharray="4"/>')
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{W_SVG}" height="{H + 20}">'
            f'{"".join(parts)}<text x="50" y="{H + 15}" font-size="11">per-view RMS (px); red: outlier '
            f"view; x: not used; dashed: median {med:.3f} px</text></svg>")


def grid_svg(res: IntrinsicsResult, values: NDArray[np.float64], vmax: float, fmt: str, note: str) -> str:
    w, h = res.camera.size
    ny, nx = values.shape
    s = W_SVG / w
    cw, ch = w / nx * s, h / ny * s
    parts = []
    for iy in range(ny):
        for ix in range(nx):
            val = float(values[iy, ix])
            parts.append(f'<rect x="{ix * cw:.1f}" y="{iy * ch:.1f}" width="{cw:.1f}" height="{ch:.1f}" '
                         f'fill="{_colour(val / vmax) if vmax > 0 else "#ccc"}" fill-opacity="0.85">'
                         f"<title>{fmt.format(val)}</title></rect>")
            parts.append(f'<text x="{ix * cw + 2:.1f}" y="{iy * ch + ch / 2 + 4:.1f}" font-size="9">'
                         f"{fmt.format(val)}</text>")
    return _frame(w, h, "".join(parts), note)


def coverage_svg(res: IntrinsicsResult) -> str:
    c = res.coverage.astype(np.float64)
    vals = np.where(c > 0, 1.0 / (1.0 + c), 1.0)
    w, h = res.camera.size
    ny, nx = c.shape
    s = W_SVG / w
    cw, ch = w / nx * s, h / ny * s
    parts = []
    for iy in range(ny):
        for ix in range(nx):
            parts.append(f'<rect x="{ix * cw:.1f}" y="{iy * ch:.1f}" width="{cw:.1f}" height="{ch:.1f}" '
                         f'fill="{_colour(vals[iy, ix] * 1.5 if c[iy, ix] == 0 else vals[iy, ix])}" '
                         f'fill-opacity="0.85"/><text x="{ix * cw + 2:.1f}" y="{iy * ch + ch / 2 + 4:.1f}" '
                         f'font-size="9">{int(c[iy, ix])}</text>')
    return _frame(w, h, "".join(parts), "observed points per cell (red: none, distortion extrapolated there)")


def distortion_svg(res: IntrinsicsResult) -> str:
    cam = res.camera
    w, h = cam.size
    s = W_SVG / w
    pts, _, _ = _grid(cam.size, 16)
    ideal = cam.undistort_points(pts)
    d = pts - ideal
    mag = np.linalg.norm(d, axis=1)
    ok = np.isfinite(mag)
    top = float(mag[ok].max()) if np.any(ok) else 0.0
    gain = (w / 16 * 0.9) / max(top, 1e-9)
    parts = []
    for (x0, y0), (dx, dy), m in zip(ideal, d, mag, strict=True):
        if not np.isfinite(m):
            continue
        parts.append(f'<line x1="{x0 * s:.1f}" y1="{y0 * s:.1f}" x2="{(x0 + dx * gain) * s:.1f}" '
                     f'y2="{(y0 + dy * gain) * s:.1f}" stroke="#a0f" stroke-width="1.2"/>'
                     f'<circle cx="{x0 * s:.1f}" cy="{y0 * s:.1f}" r="1.5" fill="#a0f"/>')
    return _frame(w, h, "".join(parts), f"distortion: ideal pinhole point -> observed pixel, largest {top:.1f} px")


def write_report(res: IntrinsicsResult, path: str | Path, cross_validation: dict[str, Any] | None = None) -> None:
    cam = res.camera
    v = res.verdict
    unc = res.uncertainty
    status = ("<p class='ok'>Calibration trustworthy for the covered region.</p>" if v["ok"] else
              "<p class='bad'>Not trustworthy: " + "".join(
                  f"<br><b>{html.escape(p['code'])}</b>: {html.escape(p['message'])}" for p in v["problems"])
              + "</p>")
    sig = res.param_sigmas
    rows = "".join(f"<tr><td>{n}</td><td>{val:.6g}</td><td>{sig[n]:.3g}</td></tr>"
                   for n, val in zip(res.param_names, np.concatenate([[cam.fx, cam.fy, cam.cx, cam.cy], cam.dist]),
                                     strict=True))
    cv_html = ""
    if cross_validation:
        cv_html = (f"<h2>Cross-validation ({cross_validation['k']} folds)</h2><p>projection difference between "
                   f"fold solutions: RMS {cross_validation['projection_difference_rms_px']:.3f} px, max "
                   f"{cross_validation['projection_difference_max_px']:.3f} px (expected from the folds' "
                   f"uncertainty: {cross_validation['expected_from_uncertainty_px']:.3f} px)</p>")
    corners = ", ".join(f"{k} {val:.3f}" for k, val in unc["corners_px"].items() if val is not None)
    umax = float(np.nanmax(res.uncertainty_map_px)) if np.any(np.isfinite(res.uncertainty_map_px)) else 1.0
    doc = f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>cellctl calibration report</title>
<style>body{{font-family:sans-serif;max-width:720px;margin:auto}} .ok{{color:#070;font-weight:bold}}
.bad{{color:#b00}} td{{padding:0 8px}} table{{border-collapse:collapse}} tr:nth-child(even){{background:#eee}}</style>
</head><body><h1>Camera calibration: {html.escape(cam.model)} {cam.width}x{cam.height}</h1>
{status}
<p>RMS reprojection error {res.rms_px:.3f} px over {sum(x.used for x in res.views)} views;
projection uncertainty (1&sigma;) over the covered region {unc['projection_rms_px']} px,
whole image {unc['projection_rms_whole_image_px']} px; centre {unc['centre_px']} px; corners {corners} px.</p>
<table><tr><th>parameter</th><th>value</th><th>1&sigma;</th></tr>{rows}</table>
{cv_html}
<h2>Residual vectors</h2>{residual_svg(res)}
<h2>Per-view RMS</h2>{view_bars_svg(res)}
<h2>Coverage</h2>{coverage_svg(res)}
<h2>Distortion field</h2>{distortion_svg(res)}
<h2>Projection uncertainty (px, 1&sigma;)</h2>{grid_svg(res, res.uncertainty_map_px, max(umax, 0.5), "{:.2f}",
                                                         "red at >= max(0.5 px, largest value)")}
</body></html>
"""
    Path(path).write_text(doc)
