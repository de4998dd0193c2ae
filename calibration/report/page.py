"""The report page's building blocks: the page, the verdict, tables, numbers rounded for people."""

from __future__ import annotations

import html
import math
from typing import Any

import numpy as np

CSS = """body{font-family:sans-serif;max-width:980px;margin:1em auto;padding:0 1em;color:#222}
h1{font-size:1.4em}h2{font-size:1.1em;margin-top:1.6em;border-bottom:1px solid #ccc}
.ok{color:#070;font-weight:bold}.bad{color:#b00;font-weight:bold}
table{border-collapse:collapse;margin:.5em 0}td,th{padding:2px 10px;text-align:left;border-bottom:1px solid #eee}
td.num{text-align:right;font-variant-numeric:tabular-nums}.note{color:#555;font-size:.85em;margin-top:0}
.thumbs{display:flex;flex-wrap:wrap;gap:6px}.thumb{margin:0;font-size:.75em;text-align:center}
.thumb.rejected{opacity:.6}.plots{display:flex;flex-wrap:wrap;gap:12px}svg.plot{max-width:100%;height:auto}
@page{size:A4;margin:12mm}
@media print{body{max-width:none;margin:0;padding:0;font-size:10pt;color:#000}h2{break-after:avoid}
table,tr,figure,svg.plot,.thumb{break-inside:avoid}.plots{display:block}
svg.plot{display:block;margin:0 auto 4mm;max-height:120mm}.ok,.bad{color:#000}.bad{text-decoration:underline}}"""


def esc(text: object) -> str:
    """``text`` escaped for HTML (quotes included)."""
    return html.escape(str(text), quote=True)


def fmt(v: float | None, digits: int = 3) -> str:
    """A number rounded for people: ``digits`` significant figures, no exponent for usual sizes."""
    if v is None or not math.isfinite(v):
        return "–"
    if v == 0:
        return "0"
    a = abs(v)
    if 1e-3 <= a < 1e6:
        decimals = max(0, digits - 1 - math.floor(math.log10(a)))
        return f"{v:.{decimals}f}"
    return f"{v:.{digits - 1}e}"


def page(title: str, body: str) -> str:
    """A self-contained HTML page (its style inline, no scripts)."""
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
    """The summary table: one figure per row."""
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
