"""The drift re-solve's part of a hand-eye report: the shift it corrects and the drift history behind it.

A hand-eye version made by ``POST /drift/resolve`` carries ``drift_resolve`` (cellctl.drift): the
calibration it re-solved, the camera's shift (mm, degrees), the fiducials' fit and the drift checks
of the calibration it replaces (oldest first). Pure: the result in, HTML out.
"""

from __future__ import annotations

import math
import time
from typing import Any

from calibration.report.page import esc, fmt, table


def drift_html(res: dict[str, Any]) -> str:
    """The section, or "" when the calibration is not a drift re-solve."""
    d = res.get("drift_resolve")
    if not isinstance(d, dict):
        return ""
    rows = [("re-solved from calibration", esc(d.get("from_calibration_id"))),
            ("the camera moved", f"{fmt(_n(d.get('shift_mm')))} mm, turned {fmt(_n(d.get('shift_deg')), 4)} deg"),
            ("fiducials seen, fit RMS", f"{esc(d.get('fiducials_seen'))}, {fmt(_n(d.get('rms_px')))} px"),
            ("pose uncertainty (1 sigma)", f"{fmt(_n(d.get('sigma_trans_mm')))} mm, "
                                            f"{fmt(_n(d.get('sigma_rot_deg')), 4)} deg")]
    history = [h for h in d.get("history") or [] if isinstance(h, dict)]
    body = "<h2>Drift re-solve</h2>" + table(rows)
    if history:
        lines = "".join(
            f"<tr><td>{_when(_n(h.get('t')))}</td>"
            f"<td>{fmt(_n(h.get('drift_mm')))}</td><td>{fmt(_n(h.get('drift_deg')), 4)}</td>"
            f"<td>{esc(h.get('state'))}</td><td>{esc(h.get('rule') or '')}</td></tr>" for h in history)
        body += (f"<h3>Drift checks of calibration {esc(d.get('from_calibration_id'))} (the last {len(history)})</h3>"
                 "<table class='grid'><tr><th>time</th><th>drift mm</th><th>drift deg</th><th>state</th>"
                 f"<th>rule</th></tr>{lines}</table>")
    return body


def _when(t: float) -> str:
    return esc(time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))) if math.isfinite(t) else "–"


def _n(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x
