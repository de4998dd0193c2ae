"""One HTML calibration report for the CLI and the service: camera, hand-eye and n-point.

:func:`calibration_report` takes what the store keeps for a calibration (its result JSON and its
inputs) and returns a self-contained page: inline SVG plots with axes, ticks and colour bars in
physical units, no scripts, no external files. Numbers are rounded to what their uncertainty
supports; the text quotes the same figures the plots show.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from calibration import CalibrationError
from calibration.report import camera as rc
from calibration.report.svg import Axes, bars, esc, fmt
from calibration.targets import Target, target_from_dict

CSS = """body{font-family:sans-serif;max-width:980px;margin:1em auto;padding:0 1em;color:#222}
h1{font-size:1.4em}h2{font-size:1.1em;margin-top:1.6em;border-bottom:1px solid #ccc}
.ok{color:#070;font-weight:bold}.bad{color:#b00;font-weight:bold}
table{border-collapse:collapse;margin:.5em 0}td,th{padding:2px 10px;text-align:left;border-bottom:1px solid #eee}
td.num{text-align:right;font-variant-numeric:tabular-nums}.note{color:#555;font-size:.85em;margin-top:0}
.thumbs{display:flex;flex-wrap:wrap;gap:6px}.thumb{margin:0;font-size:.75em;text-align:center}
.thumb.rejected{opacity:.6}.plots{display:flex;flex-wrap:wrap;gap:12px}"""


class ReportError(CalibrationError):
    """The stored calibration lacks what its report needs; the message says what."""


def page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
            f"<style>{CSS}</style></head><body><h1>{esc(title)}</h1>{body}</body></html>")


def verdict_html(verdict: dict[str, Any] | None) -> str:
    if verdict is None:
        return "<p>Verdict: none is computed for this kind of calibration; judge it by the figures below.</p>"
    if verdict.get("ok"):
        return "<p class='verdict ok'>Verdict: OK — trustworthy for the covered region.</p>"
    items = "".join(f"<li><b>{esc(p.get('code', ''))}</b>: {esc(p.get('message', ''))}</li>"
                    for p in verdict.get("problems", []))
    return f"<p class='verdict bad'>Verdict: NOT OK — what to do:</p><ul class='problems'>{items}</ul>"


def table(rows: list[tuple[str, str]]) -> str:
    return "<table class='summary'>" + "".join(f"<tr><th>{esc(k)}</th><td class='num'>{esc(v)}</td></tr>"
                                               for k, v in rows) + "</table>"


def with_sigma(value: float, sigma: float | None) -> tuple[str, str]:
    """``value`` rounded to two significant figures of its ``sigma`` (both as text)."""
    if sigma is None or not math.isfinite(sigma) or sigma <= 0:
        return fmt(value, 6), "–"
    decimals = max(0, 1 - math.floor(math.log10(sigma)))
    return f"{value:.{decimals}f}", f"{sigma:.{decimals}f}"


def matrix_html(name: str, T: Any) -> str:
    """A 4x4 pose as a table: rotation to 5 decimals, translation in mm to 0.01."""
    M = np.asarray(T, dtype=np.float64)
    rows = []
    for i in range(3):
        cells = "".join(f"<td class='num'>{M[i, j]:.5f}</td>" for j in range(3))
        rows.append(f"<tr>{cells}<td class='num'>{M[i, 3] * 1e3:.2f} mm</td></tr>")
    return f"<p><b>{esc(name)}</b></p><table class='matrix'>{''.join(rows)}</table>"


# ------------------------------------------------------------------------------------------ camera


def camera_html(rep: rc.CameraReport, cross_validation: dict[str, Any] | None = None) -> str:
    res, cam = rep.result, rep.camera
    unc = res.get("uncertainty") or {}
    umap = rep.uncertainty_map_px
    corners = [umap[0, 0], umap[0, -1], umap[-1, 0], umap[-1, -1]]
    finite_corners = [c for c in corners if math.isfinite(c)]
    n_rejected = sum(not v.used for v in rep.views)
    rows = [("model", f"{cam.model}, {cam.width} x {cam.height} px"),
            ("RMS reprojection error", f"{fmt(res.get('rms_px') or math.nan)} px"),
            ("views used / rejected", f"{len(rep.used)} / {n_rejected}"),
            ("points used", str(res.get("n_points_used", sum(len(v.uv) for v in rep.used)))),
            ("projection uncertainty, covered region (RMS, 1 sigma)",
             f"{fmt(unc.get('projection_rms_px') or math.nan)} px"),
            ("projection uncertainty, whole image (RMS)",
             f"{fmt(unc.get('projection_rms_whole_image_px') or math.nan)} px"),
            ("projection uncertainty, corner cells of the map (largest)",
             f"{fmt(max(finite_corners)) if finite_corners else '–'} px")]
    params = res.get("parameters") or {}
    names = params.get("names") or []
    sig = params.get("sigma") or []
    values = [cam.fx, cam.fy, cam.cx, cam.cy, *[float(x) for x in cam.dist]]
    prow = []
    for k, n in enumerate(names):
        if k < len(values):
            v, s = with_sigma(values[k], sig[k] if k < len(sig) else None)
            prow.append(f"<tr><td>{esc(n)}</td><td class='num'>{v}</td><td class='num'>{s}</td></tr>")
    cv = ""
    if cross_validation and "projection_difference_rms_px" in cross_validation:
        cv = (f"<h2>Cross-validation ({cross_validation.get('k')} folds)</h2><p>projection difference between fold "
              f"solutions: RMS {fmt(cross_validation['projection_difference_rms_px'])} px, largest "
              f"{fmt(cross_validation.get('projection_difference_max_px') or math.nan)} px (expected from the "
              f"folds' uncertainty: {fmt(cross_validation.get('expected_from_uncertainty_px') or math.nan)} px)</p>")
    return (verdict_html(res.get("verdict")) + table(rows)
            + "<h2>Parameters</h2><table class='params'><tr><th>parameter</th><th>value</th><th>1 sigma</th></tr>"
            + "".join(prow) + "</table>" + cv
            + "<h2>Residuals</h2>" + rc.residual_figure(rep) + rc.residual_histogram(rep)
            + "<h2>Per-view RMS</h2>" + rc.view_bars(rep)
            + "<h2>Rejected and outlier views</h2>" + rc.rejected_table(rep)
            + "<h2>Projection uncertainty and valid region</h2>" + rc.uncertainty_figure(rep)
            + "<h2>Coverage</h2>" + rc.coverage_figure(rep)
            + "<h2>Lens distortion</h2>" + rc.distortion_figure(rep)
            + "<h2>Views</h2>" + rc.thumbnails(rep))


def _camera_inputs(inputs: dict[str, Any], result: dict[str, Any]) -> tuple[list[dict[str, Any]], Target] | None:
    """The stored detections and target, or None when the calibration was stored without them."""
    target_desc = inputs.get("target") or result.get("target_description")
    views = list(inputs.get("views") or [])
    if not isinstance(target_desc, dict) or not views:
        return None
    return views, target_from_dict(target_desc, "stored target")


def camera_html_without_detections(rep: rc.CameraReport) -> str:
    """The report of a camera stored without its detections (imported): no residual plots."""
    note = ("<p class='note'>This calibration was stored without its detections (e.g. imported), so residual, "
            "coverage and per-view plots cannot be drawn; the uncertainty map treats the whole image as covered.</p>")
    full = camera_html(rep)
    keep = full[:full.index("<h2>Residuals</h2>")]
    return (keep + note + "<h2>Projection uncertainty</h2>" + rc.uncertainty_figure(rep)
            + "<h2>Lens distortion</h2>" + rc.distortion_figure(rep))


# ---------------------------------------------------------------------------------------- hand-eye


def handeye_html(res: dict[str, Any]) -> str:
    unc = res.get("uncertainty") or {}
    quality = res.get("quality") or {}
    noise = res.get("robot_noise") or {}
    loo = quality.get("loo_prediction_rms_px")
    rows = [("setup", str(res.get("setup"))),
            ("held-out prediction (leave-one-out RMS, the primary figure)", f"{fmt(loo or math.nan)} px"),
            ("fit RMS", f"{fmt(res.get('rms_px') or math.nan)} px"),
            ("uncertainty of the hand-eye rotation (1 sigma)", f"{fmt(unc.get('rot_deg') or math.nan)} deg"),
            ("uncertainty of the hand-eye translation (1 sigma)", f"{fmt(unc.get('trans_mm') or math.nan)} mm"),
            ("robot noise model", f"{fmt(noise.get('sigma_mm') or math.nan)} mm, "
                                  f"{fmt(noise.get('sigma_deg') or math.nan)} deg"
                                  f"{' (estimated)' if noise.get('estimated') else ''}")]
    mats = "".join(matrix_html(k, res[k]) for k in ("T_tool_cam", "T_base_target", "T_base_cam", "T_tool_target")
                   if k in res)
    poses = res.get("poses") or []
    labels = [str(p.get("image", k)) for k, p in enumerate(poses)]
    figs = ""
    if poses:
        figs = (bars(labels, [p.get("rms_px") or math.nan for p in poses], "px",
                     "Per station: fit RMS (bars) and held-out prediction (black marks)", "px",
                     second=[p.get("loo_rms_px") for p in poses], second_label="held-out prediction",
                     lines=[(loo, "#c00", f"prediction RMS {fmt(loo)} px")] if loo else [])
                + bars(labels, [p.get("loo_mm") or math.nan for p in poses], "mm",
                       "Per station: held-out target position error", "mm")
                + bars(labels, [p.get("robot_correction_mm") or math.nan for p in poses], "mm",
                       "Per station: robot pose correction of the refinement", "mm",
                       lines=[(float(noise["sigma_mm"]), "#090", f"noise model {fmt(noise['sigma_mm'])} mm")]
                       if noise.get("sigma_mm") else []))
    return verdict_html(res.get("verdict")) + table(rows) + "<h2>Transforms</h2>" + mats + "<h2>Stations</h2>" + figs


# ----------------------------------------------------------------------------------------- n-point


def npoint_html(res: dict[str, Any], inputs: dict[str, Any]) -> str:
    pairs = inputs.get("pairs") or []
    resid = np.asarray(res.get("residuals_mm") or [], dtype=np.float64)
    resid = resid.reshape(-1, 2) if resid.ndim == 2 else resid.reshape(-1, 1)  # vectors, or lengths per mark
    loo = res.get("loo_rms_mm") or {}
    rows = [("model", str(res.get("model"))), ("RMS residual", f"{fmt(res.get('rms_mm') or math.nan)} mm"),
            ("leave-one-out RMS by model", ", ".join(f"{k} {fmt(v)} mm" for k, v in loo.items()) or "–"),
            ("marks", str(len(resid)))]
    figs = ""
    if len(pairs) == len(resid) and len(resid):
        xy = np.array([[p["x_mm"], p["y_mm"]] for p in pairs], dtype=np.float64)
        figs = _bubbles(xy, resid) + bars([f"mark {p.get('mark_id', k)}" for k, p in enumerate(pairs)],
                                          list(np.linalg.norm(resid, axis=1)), "mm", "Residual per mark",
                                          "residual (mm)")
    return verdict_html(res.get("verdict")) + table(rows) + "<h2>Residuals</h2>" + figs


def _bubbles(xy: Any, resid: Any) -> str:
    """Residual bubbles at the marks' robot positions: area by length, with a scale legend."""
    mags = np.linalg.norm(resid, axis=1)
    pad = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0) * 0.15
    ax = Axes((float(xy[:, 0].min()) - pad, float(xy[:, 0].max()) + pad),
              (float(xy[:, 1].min()) - pad, float(xy[:, 1].max()) + pad), 480, 380,
              title="Residuals at the marks (robot frame)", xlabel="x (mm)", ylabel="y (mm)", right_margin=110)
    top = max(float(mags.max()), 1e-6)
    r_max = 22.0
    for (x, y), m in zip(xy, mags, strict=True):
        ax.circle(float(x), float(y), max(2.0, r_max * math.sqrt(m / top)), "rgba(74,127,181,0.5)", "#24527a",
                  f"({fmt(float(x))}, {fmt(float(y))}) mm: {fmt(float(m))} mm")
    legend = []
    lx = ax.left + ax.w + 40
    for k, m in enumerate((top, top / 4)):
        cy = ax.top + 40 + k * 60
        legend.append(f'<circle cx="{lx}" cy="{cy}" r="{r_max * math.sqrt(m / top):.1f}" fill="rgba(74,127,181,0.5)" '
                      f'stroke="#24527a"/><text x="{lx + 26}" y="{cy + 4}" font-size="10">{esc(fmt(m))} mm</text>')
    return ax.svg("plot bubbles", "".join(legend))


# ---------------------------------------------------------------------------------------- dispatch


def calibration_report(kind: str, result: dict[str, Any], inputs: dict[str, Any] | None = None, title: str = "",
                       cross_validation: dict[str, Any] | None = None, images: dict[str, bytes] | None = None) -> str:
    """The HTML report of a stored calibration (``kind``: camera, handeye, npoint)."""
    inputs = inputs or {}
    if kind == "camera":
        found = _camera_inputs(inputs, result)
        if found is None:
            body = camera_html_without_detections(rc.build(result, [], None, images))
        else:
            body = camera_html(rc.build(result, found[0], found[1], images), cross_validation)
    elif kind == "handeye":
        body = handeye_html(result)
    elif kind == "npoint":
        body = npoint_html(result, inputs)
    else:
        raise ReportError(f"no report for calibrations of kind {kind!r}")
    return page(title or f"{kind} calibration", body)


def report_json(kind: str, result: dict[str, Any], inputs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report's figures as JSON (camera: the plotted grids and per-view figures)."""
    if kind == "camera":
        found = _camera_inputs(inputs or {}, result)
        return rc.build(result, *(found or ([], None))).to_json()
    keys = {"handeye": ("setup", "rms_px", "quality", "uncertainty", "poses", "verdict"),
            "npoint": ("model", "rms_mm", "loo_rms_mm", "residuals_mm", "verdict")}.get(kind, ())
    out = {k: result[k] for k in keys if k in result}
    if isinstance(out.get("uncertainty"), dict):
        out["uncertainty"] = {k: v for k, v in out["uncertainty"].items() if "covariance" not in k}
    return {"kind": kind, **out}
