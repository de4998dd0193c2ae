"""The belt (``conveyor-calibrate``) part of the report: direction, ticks per metre, their uncertainty and the
sightings' residual from the fitted line."""

from __future__ import annotations

from typing import Any

from calibration.report.page import esc, fmt, table, verdict_html


def conveyor_html(res: dict[str, Any], inputs: dict[str, Any]) -> str:
    d = res.get("direction_base") or [float("nan")] * 3
    rows = [("direction in the base frame", "[" + ", ".join(fmt(v, 5) for v in d) + "]"),
            ("ticks per metre", f"{fmt(res.get('ticks_per_m'), 7)} ± {fmt(res.get('sigma_ticks_per_m'))} (1-σ)"),
            ("direction 1-σ (deg)", fmt(res.get("sigma_direction_deg"))),
            ("sightings", str(res.get("n_sightings", len(inputs.get("sightings") or [])))),
            ("travel between the first and last sighting (mm)", fmt(res.get("travel_mm"))),
            ("RMS distance of the sightings from the line (mm)", fmt(res.get("rms_mm")))]
    sights = inputs.get("sightings") or []
    listing = "".join(f"<tr><td class='num'>{esc(str(s['ticks']))}</td><td class='num'>"
                      + ", ".join(fmt(v * 1e3, 5) for v in s["origin_m"])
                      + f"</td><td class='num'>{fmt(s.get('rms_px'))}</td></tr>" for s in sights)
    body = verdict_html(res.get("verdict")) + table(rows)
    if listing:
        body += ("<h2>Sightings</h2><table class='summary'><tr><th>encoder count</th><th>target origin, base "
                 "frame (mm)</th><th>pose RMS (px)</th></tr>" + listing + "</table>")
    return body
