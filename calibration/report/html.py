"""One HTML calibration report for the CLI and the service: camera, hand-eye and n-point.

:func:`calibration_report` takes what the store keeps for a calibration (its result JSON and its
inputs) and returns a self-contained page: inline SVG plots with axes, ticks and colour bars in
physical units, no scripts, no external files. Numbers are rounded to what their uncertainty
supports; the text quotes the same figures the plots show.
"""

from __future__ import annotations

import math
from typing import Any

from calibration import CalibrationError
from calibration.report import camera as rc
from calibration.report import camera_plots as cp
from calibration.report.handeye import handeye_html
from calibration.report.npoint import npoint_html
from calibration.report.page import esc, fmt, page, table, verdict_html, with_sigma
from calibration.targets import Target, target_from_dict


class ReportError(CalibrationError):
    """The stored calibration lacks what its report needs; the message says what."""


# ------------------------------------------------------------------------------------------ camera


def camera_summary(rep: rc.CameraReport) -> str:
    """The verdict and the summary table of a camera report (the counts as the job reported them)."""
    res, cam = rep.result, rep.camera
    unc = res.get("uncertainty") or {}
    umap = rep.uncertainty_map_px
    corners = [umap[0, 0], umap[0, -1], umap[-1, 0], umap[-1, -1]]
    finite_corners = [c for c in corners if math.isfinite(c)]
    n_rejected = sum(not v.used for v in rep.views)
    rows = [("model", f"{cam.model}, {cam.width} x {cam.height} px"),
            ("RMS reprojection error", f"{fmt(res.get('rms_px') or math.nan)} px"),
            *([("views tried by the capture / rejected there (not calibrated)",
                f"{rep.capture['views_tried']} / {rep.capture['views_rejected']}")] if rep.capture else []),
            ("views calibrated: used / rejected by the solver", f"{len(rep.used)} / {n_rejected}"),
            ("points used", str(res.get("n_points_used", sum(len(v.uv) for v in rep.used)))),
            ("projection uncertainty, covered region (RMS, 1 sigma)",
             f"{fmt(unc.get('projection_rms_px') or math.nan)} px"),
            ("projection uncertainty, whole image (RMS)",
             f"{fmt(unc.get('projection_rms_whole_image_px') or math.nan)} px"),
            ("projection uncertainty, corner cells of the map (largest)",
             f"{fmt(max(finite_corners)) if finite_corners else '–'} px")]
    warp = res.get("board_warp")
    if warp:
        h, s = warp.get("height_mm") or [math.nan] * 2, warp.get("sigma_mm") or [math.nan] * 2
        rows.append(("board warp: the target's bow at its centre line along x / y (1 sigma)",
                     f"{fmt(h[0])} ± {fmt(s[0])} mm / {fmt(h[1])} ± {fmt(s[1])} mm"))
    return verdict_html(res.get("verdict")) + table(rows)


def parameters_html(rep: rc.CameraReport) -> str:
    """The camera's parameters, each rounded to its 1-sigma uncertainty."""
    res, cam = rep.result, rep.camera
    params = res.get("parameters") or {}
    names = params.get("names") or []
    sig = params.get("sigma") or []
    values = [cam.fx, cam.fy, cam.cx, cam.cy, *[float(x) for x in cam.dist]]
    prow = []
    shown = 7 if cam.model == "splined" else len(names)   # the spline's control values: a count, not a table
    for k, n in enumerate(names[:shown]):
        if k < len(values):
            v, s = with_sigma(values[k], sig[k] if k < len(sig) else None)
            prow.append(f"<tr><td>{esc(n)}</td><td class='num'>{v}</td><td class='num'>{s}</td></tr>")
    if len(names) > shown:
        prow.append(f"<tr><td colspan='3'>and {len(names) - shown} spline control values (cam.json "
                    "<code>dist</code>)</td></tr>")
    return ("<h2>Parameters</h2><table class='params'><tr><th>parameter</th><th>value</th><th>1 sigma</th></tr>"
            + "".join(prow) + "</table>")


def camera_html(rep: rc.CameraReport, cross_validation: dict[str, Any] | None = None) -> str:
    """The camera report's body: summary, parameters, cross-validation, figures, thumbnails."""
    cv = ""
    if cross_validation and "projection_difference_rms_px" in cross_validation:
        reps = int(cross_validation.get("repeats") or 1)
        spread = cross_validation.get("spread_px")
        over = (f", median over {reps} partitions of the views (10-90 %: {fmt(spread[0])}-{fmt(spread[1])} px)"
                if reps > 1 and spread else "")
        cv = (f"<h2>Cross-validation ({cross_validation.get('k')} folds)</h2><p>projection difference between fold "
              f"solutions{over}: RMS {fmt(cross_validation['projection_difference_rms_px'])} px, largest "
              f"{fmt(cross_validation.get('projection_difference_max_px') or math.nan)} px (expected from the "
              f"folds' uncertainty: {fmt(cross_validation.get('expected_from_uncertainty_px') or math.nan)} px)</p>")
        sel = cross_validation.get("model_selection")
        if sel and sel.get("candidates"):
            cv += ("<p>Model chosen by cross-validation (" + esc(sel.get("rule", "")) + "):</p><table><tr>"
                   "<th>model</th><th>board warp</th><th>RMS (px)</th><th>cross-validation (px)</th>"
                   "<th>expected (px)</th><th></th></tr>")
            for c in sel["candidates"]:
                name = c["model"] + (" (regularised)" if c.get("regularised") else "")
                cv += (f"<tr><td>{esc(name)}</td><td>{'yes' if c['board_warp'] else 'no'}</td>"
                       f"<td class='num'>{fmt(c.get('rms_px', math.nan))}</td>"
                       f"<td class='num'>{fmt(c.get('cross_validation_px', math.nan))}</td>"
                       f"<td class='num'>{fmt(c.get('expected_px', math.nan))}</td>"
                       f"<td>{'chosen' if c.get('chosen') else esc(c.get('refused', ''))}</td></tr>")
            cv += "</table>"
    return (camera_summary(rep) + parameters_html(rep) + cv
            + "<h2>Residuals</h2>" + cp.residual_figure(rep) + cp.residual_histogram(rep)
            + "<h2>Residuals against the radius</h2>" + cp.radius_figure(rep)
            + "<h2>Per-view RMS</h2>" + cp.view_bars(rep)
            + "<h2>Rejected and outlier views</h2>" + cp.rejected_table(rep)
            + "<h2>Projection uncertainty and valid region</h2>" + cp.uncertainty_figure(rep)
            + "<h2>Coverage</h2>" + cp.coverage_figure(rep)
            + "<h2>Lens distortion</h2>" + cp.distortion_figure(rep)
            + "<h2>Views</h2>" + cp.thumbnails(rep))


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
    return (camera_summary(rep) + parameters_html(rep) + note + "<h2>Projection uncertainty</h2>"
            + cp.uncertainty_figure(rep)
            + "<h2>Lens distortion</h2>" + cp.distortion_figure(rep))


# ---------------------------------------------------------------------------------------- dispatch


def calibration_report(kind: str, result: dict[str, Any], inputs: dict[str, Any] | None = None, title: str = "",
                       cross_validation: dict[str, Any] | None = None, images: dict[str, bytes] | None = None) -> str:
    """The HTML report of a stored calibration (``kind``: camera, handeye, npoint, conveyor)."""
    inputs = inputs or {}
    if kind == "camera":
        found = _camera_inputs(inputs, result)
        if found is None:
            body = camera_html_without_detections(rc.build(result, [], None, images, inputs))
        else:
            body = camera_html(rc.build(result, found[0], found[1], images, inputs), cross_validation)
    elif kind == "handeye":
        body = handeye_html(result)
    elif kind == "npoint":
        body = npoint_html(result, inputs)
    elif kind == "conveyor":
        from calibration.report.conveyor import conveyor_html

        body = conveyor_html(result, inputs)
    else:
        raise ReportError(f"no report for calibrations of kind {kind!r}")
    return page(title or f"{kind} calibration", body)


def report_json(kind: str, result: dict[str, Any], inputs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report's figures as JSON (camera: the plotted grids and per-view figures)."""
    if kind == "camera":
        found = _camera_inputs(inputs or {}, result)
        views, target = found or ([], None)
        return rc.build(result, views, target, inputs=inputs or {}).to_json()
    keys = {"handeye": ("setup", "method", "dof", "rms_px", "quality", "uncertainty", "poses", "leave_one_out",
                        "verdict"),
            "npoint": ("model", "rms_mm", "loo_rms_mm", "residuals_mm", "verdict"),
            "conveyor": ("direction_base", "ticks_per_m", "sigma_ticks_per_m", "sigma_direction_deg", "rms_mm",
                         "n_sightings", "travel_mm", "verdict")}.get(kind, ())
    out = {k: result[k] for k in keys if k in result}
    if isinstance(out.get("uncertainty"), dict):
        out["uncertainty"] = {k: v for k, v in out["uncertainty"].items() if "covariance" not in k}
    return {"kind": kind, **out}
