"""The hand-eye part of the report: the summary, the transforms, and per station (named on the axis)
the residuals in px, mm and degrees.

Per station, from the stored result: the fit RMS and the held-out prediction in px; the held-out
target pose error in mm and degrees (6-DOF: ``poses[k].loo_mm`` / ``loo_deg``; 4-DOF:
``leave_one_out.per_pose[k].position_mm`` / ``rotation_deg``; a measured frame:
``single_station_diff_mm`` / ``_deg``); the refinement's robot pose correction in mm and degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from calibration.report import plots as pl
from calibration.report.camera_plots import RESIDUAL_BAND
from calibration.report.drift import drift_html
from calibration.report.page import esc, fmt, matrix_html, table, verdict_html

POSITION_BAND = pl.Band(0.5, 2.0, "mm")
"""Held-out target position error: within 0.5 mm a pick lands where it should; 2 mm and more misses."""
ROTATION_BAND = pl.Band(0.05, 0.25, "deg")
"""Held-out target rotation error: 0.05 deg moves a point 0.5 m away by 0.4 mm, 0.25 deg by 2 mm."""


@dataclass
class Station:
    """One station's figures (NaN where the result has none)."""

    name: str
    rms_px: float
    heldout_px: float
    heldout_mm: float
    heldout_deg: float
    correction_mm: float
    correction_deg: float


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) else math.nan


def stations(res: dict[str, Any]) -> list[Station]:
    """The per-station figures of a 6-DOF, 4-DOF or measured-frame hand-eye result."""
    poses = res.get("poses") or []
    per_pose = (res.get("leave_one_out") or {}).get("per_pose") or []
    out = []
    for k, p in enumerate(poses):
        loo = per_pose[k] if k < len(per_pose) and isinstance(per_pose[k], dict) else {}
        out.append(Station(
            str(p.get("image", k)), _num(p.get("rms_px")),
            _num(p.get("loo_rms_px", loo.get("rms_px"))),
            _num(p.get("loo_mm", loo.get("position_mm", p.get("single_station_diff_mm")))),
            _num(p.get("loo_deg", loo.get("rotation_deg", p.get("single_station_diff_deg")))),
            _num(p.get("robot_correction_mm")), _num(p.get("robot_correction_deg"))))
    return out


def _pair_figure(names: list[str], mm: list[float], deg: list[float], css: str, title: str,
                 bands: tuple[pl.Band, pl.Band], what: tuple[str, str]) -> str:
    """Two bar charts side by side, mm and deg per station; each bar carries its number."""
    with pl.canvas(min(960.0, 2 * pl.bars_width_px(len(names)) * 0.6), 320) as fig:
        ax_mm, ax_deg = fig.subplots(1, 2)
        pl.named_bars(ax_mm, names, mm, bands[0], "bar mm")
        ax_mm.set(title=f"{what[0]} (mm)", ylabel="mm")
        pl.named_bars(ax_deg, names, deg, bands[1], "bar deg")
        ax_deg.set(title=f"{what[1]} (deg)", ylabel="deg")
        for ax in (ax_mm, ax_deg):
            ax.legend(loc="upper left", fontsize=7)
        fig.suptitle(title, fontsize=10, fontweight="bold", x=0.01, ha="left")
        return pl.svg(fig, css, title)


def _px_figure(st: list[Station], loo: float | None) -> str:
    title = "Per station: fit RMS (bars) and held-out prediction (black marks)"
    with pl.canvas(pl.bars_width_px(len(st)), 320) as fig:
        ax = fig.subplots()
        held = [s.heldout_px for s in st]
        pl.named_bars(ax, [s.name for s in st], [s.rms_px for s in st], RESIDUAL_BAND, "bar px",
                      note=not any(math.isfinite(h) for h in held))
        if any(math.isfinite(h) for h in held):
            marks = ax.scatter(range(len(st)), held, marker="_", s=120, lw=2.5, color="#000", zorder=4,
                               label="held-out prediction")
            pl.tag(marks, "heldout-px", values=" ".join(f"{h:.4g}" for h in held))
            ax.set_ylim(0.0, max(ax.get_ylim()[1], max((h for h in held if math.isfinite(h)), default=0.0) * 1.15))
        if loo:
            ax.axhline(loo, color="#c00", lw=1.0, ls=":", label=f"prediction RMS {fmt(loo)} px")
        ax.set(title=title, ylabel="px")
        ax.legend(loc="upper left", ncols=2, fontsize=7)
        return pl.svg(fig, "plot stations-px", title)


def _station_table(st: list[Station]) -> str:
    head = ("<tr><th>station</th><th>fit RMS px</th><th>held-out px</th><th>held-out mm</th><th>held-out deg</th>"
            "<th>robot correction mm</th><th>robot correction deg</th></tr>")
    rows = "".join(f"<tr><td>{esc(s.name)}</td>" + "".join(
        f"<td class='num'>{fmt(v)}</td>" for v in (s.rms_px, s.heldout_px, s.heldout_mm, s.heldout_deg,
                                                    s.correction_mm, s.correction_deg)) + "</tr>" for s in st)
    return f"<table class='stations'>{head}{rows}</table>"


def handeye_html(res: dict[str, Any]) -> str:
    unc = res.get("uncertainty") or {}
    quality = res.get("quality") or {}
    noise = res.get("robot_noise") or {}
    loo = quality.get("loo_prediction_rms_px") or ((res.get("leave_one_out") or {}).get("rms_px") or {}).get("rms")
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
    st = stations(res)
    figs = ""
    if st:
        names = [s.name for s in st]
        figs = _px_figure(st, loo)
        if any(math.isfinite(s.heldout_mm) for s in st):
            measured = res.get("method") == "measured_frame"
            what = "single-station solution against the joint one" if measured else "held-out target pose error"
            figs += _pair_figure(names, [s.heldout_mm for s in st], [s.heldout_deg for s in st], "plot heldout",
                                 f"Per station: {what}", (POSITION_BAND, ROTATION_BAND),
                                 ("position difference", "rotation difference") if measured
                                 else ("held-out position error", "held-out rotation error"))
        if any(math.isfinite(s.correction_mm) for s in st):
            s_mm, s_deg = _num(noise.get("sigma_mm")), _num(noise.get("sigma_deg"))
            bands = (pl.Band(3 * s_mm, 6 * s_mm, "mm", "3 sigma", "6 sigma") if s_mm > 0 else POSITION_BAND,
                     pl.Band(3 * s_deg, 6 * s_deg, "deg", "3 sigma", "6 sigma") if s_deg > 0 else ROTATION_BAND)
            figs += _pair_figure(names, [s.correction_mm for s in st], [s.correction_deg for s in st],
                                 "plot corrections", "Per station: robot pose correction of the refinement "
                                 "(against the noise model)", bands, ("position correction", "rotation correction"))
        figs += _station_table(st)
    return (verdict_html(res.get("verdict")) + table(rows) + drift_html(res) + "<h2>Transforms</h2>" + mats
            + "<h2>Stations</h2>" + figs)
