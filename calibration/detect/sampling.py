"""Bilinear sampling of an image at sub-pixel positions: the one sampler of ``calibration.detect``.

Positions are pixel-centre coordinates (px, ``(u, v)`` = column, row); outside the image the
border value is repeated. Two accuracies:

- ``exact=False`` (default): ``cv2.remap``, which rounds every position to 1/32 px (a bias of up to
  0.016 px per sample). Fast; fine where many samples average that rounding out (the ~100 rays of a
  mark, a Gaussian window of gradients, the saddle fit's start).
- ``exact=True``: exact bilinear weights in numpy. For the point-symmetry corner refinement, where
  every sample of a corner would carry the same rounding.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

REMAP_MAX_ROWS = 30000
"""cv2.remap's maps are limited to 32767 rows and columns: longer inputs are sampled in parts."""


def sample_bilinear(img: NDArray[np.float32], u: FloatArray, v: FloatArray, exact: bool = False) -> FloatArray:
    """Bilinear samples (float64) of the float32 image ``img`` at positions ``(u, v)`` (px; any two
    arrays of one shape with at least one axis; the result has that shape)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if exact:
        return _exact(img, u, v)
    shape = u.shape
    mu = u.reshape(-1, shape[-1]).astype(np.float32)
    mv = v.reshape(-1, shape[-1]).astype(np.float32)
    parts = [cv2.remap(img, mu[i : i + REMAP_MAX_ROWS], mv[i : i + REMAP_MAX_ROWS], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE) for i in range(0, len(mu), REMAP_MAX_ROWS)]
    return np.concatenate(parts).reshape(shape).astype(np.float64)


def _exact(a: NDArray[np.float32], u: FloatArray, v: FloatArray) -> FloatArray:
    h, w = a.shape
    bu, bv = np.floor(u), np.floor(v)
    fu, fv = u - bu, v - bv
    u0, v0 = bu.astype(np.int64), bv.astype(np.int64)
    u1, v1 = np.clip(u0 + 1, 0, w - 1), np.clip(v0 + 1, 0, h - 1)
    u0, v0 = np.clip(u0, 0, w - 1), np.clip(v0, 0, h - 1)
    return ((1 - fv) * ((1 - fu) * a[v0, u0] + fu * a[v0, u1]) + fv * ((1 - fu) * a[v1, u0] + fu * a[v1, u1])
            ).astype(np.float64)
