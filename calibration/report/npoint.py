"""The N-point (jog-to-mark) part of the report: residual bubbles at the marks, residual per mark."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from calibration.report import plots as pl
from calibration.report.handeye import POSITION_BAND
from calibration.report.page import fmt, table, verdict_html


def _bubbles(xy: Any, mags: Any) -> str:
    """Residual bubbles at the marks' robot positions (area by length), with a scale legend."""
    top = max(float(mags.max()), 1e-6)
    title = "Residuals at the marks (robot frame)"
    with pl.canvas(560, 420, layout=None) as fig:
        ax, _ = pl.fixed_axes(fig, right_px=130)
        colours = POSITION_BAND.rgb(mags, mags)
        dots = ax.scatter(xy[:, 0], xy[:, 1], s=900.0 * mags / top, c=colours, alpha=0.7, edgecolors="#24527a")
        pl.tag(dots, "bubble", values=" ".join(f"{m:.4g}" for m in mags))
        for m in (top, top / 4):
            ax.scatter([], [], s=900.0 * m / top, color="#bbb", edgecolors="#24527a", label=f"{fmt(m)} mm")
        legend = fig.legend(title="residual", loc="upper right", labelspacing=2.0, borderpad=1.2)
        pl.tag(legend, "legend")
        pad = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0) * 0.15  # room for the largest bubble
        ax.set_xlim(float(xy[:, 0].min()) - pad, float(xy[:, 0].max()) + pad)
        ax.set_ylim(float(xy[:, 1].min()) - pad, float(xy[:, 1].max()) + pad)
        ax.set_aspect("equal", adjustable="box", anchor="W")  # millimetres alike on both axes
        ax.set(title=title, xlabel="x (mm)", ylabel="y (mm)")
        return pl.svg(fig, "plot bubbles", title)


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
        mags = np.linalg.norm(resid, axis=1)
        names = [f"mark {p.get('mark_id', k)}" for k, p in enumerate(pairs)]
        with pl.canvas(pl.bars_width_px(len(names)), 300) as fig:
            ax = fig.subplots()
            pl.named_bars(ax, names, list(mags), POSITION_BAND, "bar mark")
            ax.set(title="Residual per mark", ylabel="residual (mm)")
            ax.legend(loc="upper left", fontsize=7)
            bars = pl.svg(fig, "plot marks", "Residual per mark")
        figs = _bubbles(xy, mags) + bars
    return verdict_html(res.get("verdict")) + table(rows) + "<h2>Residuals</h2>" + figs
