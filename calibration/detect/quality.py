"""Per-image quality figures of a detection, so that a routine can reject a bad shot and say why.

- ``edge_contrast_grey``: grey-level difference between the light and dark parts of the target
  (95th minus 5th percentile inside the detected points' hull, slightly enlarged);
- ``blur_sigma_px``: the Gaussian sigma of an ideal step edge with that contrast and the observed
  steepest gradients (contrast / (sqrt(2 pi) * gradient)); a sharp, well-sampled edge gives ~0.5-0.7;
- ``coverage_fraction``: the detected points' convex hull area over the image area.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray


def image_quality(grey: NDArray[np.uint8], uv: NDArray[np.float64]) -> dict[str, float]:
    """Quality figures of the region of ``grey`` covered by the detected points ``uv``."""
    h, w = grey.shape[:2]
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 3:
        return {"edge_contrast_grey": 0.0, "blur_sigma_px": float("nan"), "coverage_fraction": 0.0}
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    area = float(cv2.contourArea(hull.astype(np.float32)))
    centre = hull.mean(axis=0)
    grown = centre + (hull - centre) * 1.15
    mask = np.zeros((h, w), dtype=np.uint8)
    cv2.fillConvexPoly(mask, np.rint(grown).astype(np.int32), 1)
    x0, y0, bw, bh = cv2.boundingRect(np.rint(grown).astype(np.int32))
    x0, y0 = max(x0 - 2, 0), max(y0 - 2, 0)
    x1, y1 = min(x0 + bw + 4, w), min(y0 + bh + 4, h)
    inside = mask[y0:y1, x0:x1].astype(bool)
    if inside.sum() < 16:
        return {"edge_contrast_grey": 0.0, "blur_sigma_px": float("nan"), "coverage_fraction": area / (w * h)}
    roi = grey[y0:y1, x0:x1]
    values = roi[inside].astype(np.float64)
    lo, hi = np.percentile(values, [5.0, 95.0])
    contrast = float(hi - lo)
    g = roi.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.hypot(gx, gy)[inside]
    g_max = float(np.percentile(mag, 99.5))
    blur = contrast / (math.sqrt(2 * math.pi) * g_max) if g_max > 0 and contrast > 0 else float("nan")
    return {"edge_contrast_grey": contrast, "blur_sigma_px": float(blur),
            "coverage_fraction": float(min(area / (w * h), 1.0))}
