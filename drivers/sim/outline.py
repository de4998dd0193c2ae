"""A flat part's outline as a mask: which points (table frame, metres) lie on the part (inside its outline,
outside its holes). The virtual cell's renderer asks it for every ray near a part."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def part_mask(outline_mm: list[list[float]], holes_mm: list[list[list[float]]], x_mm0: float, y_mm0: float,
              angle_deg: float, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Points (table frame, metres) inside a part's outline and outside its holes."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    poly = np.asarray(outline_mm, dtype=np.float64)
    radius = float(np.max(np.linalg.norm(poly, axis=1)))
    inside = np.zeros(x.shape, dtype=bool)
    # A box test on the raw coordinates first: most of a frame's points are far from every part.
    r_m = radius / 1000.0 + 1e-6
    box = (np.abs(x - x_mm0 / 1000.0) <= r_m) & (np.abs(y - y_mm0 / 1000.0) <= r_m)
    if not np.any(box):
        return inside
    dx, dy = x[box] * 1000.0 - x_mm0, y[box] * 1000.0 - y_mm0
    px, py = c * dx + s * dy, -s * dx + c * dy  # into the part frame (mm)
    near = px * px + py * py <= radius * radius
    qx, qy = px[near], py[near]
    m = _even_odd(poly, qx, qy)
    for hole in holes_mm:
        m &= ~_even_odd(np.asarray(hole, dtype=np.float64), qx, qy)
    near[near] = m
    inside[box] = near
    return inside


def _even_odd(poly: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
    inside = np.zeros(x.shape, dtype=bool)
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        crosses = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (x < xi)
    return inside
