"""Orientation response maps (LINE-MOD / line2Dup style) and the discrete pose search on them.

The image's gradient orientation is quantized into ``N_BINS`` bins over 180° (edge polarity
ignored); per bin a response map holds 0..4 by the orientation difference to that bin (through
a table), spread by a max filter so a feature that is a pixel or two off still scores.
``track`` scores a batch of candidate poses over a small neighbourhood of position and angle
by gathering each feature's response at its rotated offset.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.image import F64, U8, gradients
from vision.shape import search_kernels as sk
from vision.shape.model import LevelModel

N_BINS = 8
BIN_W = math.pi / N_BINS


def _response_table() -> U8:
    """(N_BINS, 4*N_BINS+1) responses of each feature bin to each quarter-bin orientation."""
    t = np.zeros((N_BINS, 4 * N_BINS + 1), np.uint8)  # last column: no edge
    for b in range(N_BINS):
        for qb in range(4 * N_BINS):
            d = abs(qb + 0.5 - (4.0 * b + 2.0))
            d = min(d, 4.0 * N_BINS - d)  # circular distance in quarter-bins (1 = 5.625 deg)
            t[b, qb] = int(np.clip(4 - math.floor(d * 0.5), 0, 4))  # 4 within ~11 deg, 0 beyond 45
    return t


_RESPONSE_TABLE = _response_table()


def response_maps(img: U8, thr: float, sigma: float = 0.0, spread: int = 3) -> U8:
    """(N_BINS, H, W) uint8 responses 0..4 to each orientation bin, spread by a max filter.

    ``spread`` is the max filter's size (1: none).
    """
    gx, gy = gradients(img, sigma)
    ang = cv2.phase(gx, gy, angleInDegrees=True)  # 0..360
    q = cv2.convertScaleAbs(ang, alpha=4.0 * N_BINS / 180.0, beta=-0.5)  # floor: quarter-bins 0..63
    q = cv2.bitwise_and(q, 4 * N_BINS - 1)  # orientation modulo 180 deg
    h, w = img.shape
    out = np.empty((N_BINS, h, w), np.uint8)
    # no edge (magnitude < thr) responds 0; one compiled pass for all bins (was a mask and 8 cv2.LUT),
    # the magnitude computed in it (vision.image.magnitude's bits; cv2.magnitude's depend on alignment)
    sk.response_planes(q, gx, gy, float(thr), _RESPONSE_TABLE, out)
    return spread_max(out, spread)


def spread_max(resp: U8, size: int) -> U8:
    """Max filter of each bin's responses (``size`` x ``size``; 1 returns ``resp``)."""
    if size <= 1:
        return resp
    out = np.empty_like(resp)
    kernel = np.ones((size, size), np.uint8)
    for b in range(resp.shape[0]):
        cv2.dilate(resp[b], kernel, dst=out[b])
    return out


def rotated_features(lm: LevelModel, thetas: F64, scales: F64 | None = None
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Rounded feature offsets (A, F) dx, dy and orientation bins for each angle (and scale)."""
    m = lm.points[lm.features]
    n = lm.normals[lm.features]
    k = np.ones(len(thetas)) if scales is None else scales
    c, s = (k * np.cos(thetas))[:, None], (k * np.sin(thetas))[:, None]
    dx = np.rint(c * m[:, 0] + s * m[:, 1]).astype(np.int64)
    dy = np.rint(-s * m[:, 0] + c * m[:, 1]).astype(np.int64)
    phi = np.arctan2(n[:, 1], n[:, 0])[None, :] - thetas[:, None]
    b = (np.floor(np.mod(phi, math.pi) / BIN_W).astype(np.int64)) % N_BINS
    return dx, dy, b


def track(resp: U8, lm: LevelModel, cx: NDArray[np.int64], cy: NDArray[np.int64], th: F64,
          n_steps: int = 1, reach: int = 1, scale: F64 | None = None) -> tuple[F64, F64, F64, F64]:
    """Best pose of each candidate over +-reach px and +-n_steps angle steps: (x, y, theta, score).

    With the responses spread over 3x3, reach 1 covers a candidate that is up to 2 px off.
    ``scale`` (one per candidate) sizes the model; candidates outside the image are clamped to it.
    Features outside the image score 0 (a part at the border is scored on what is visible); ties
    (the spread responses make plateaus) go to the angle nearest the prediction, and the position
    is the plateau's centre rather than its first pixel (``search_kernels.track_batch``).
    """
    if len(cx) == 0:
        e = np.zeros(0)
        return e, e.copy(), e.copy(), e.copy()
    k_s = np.ones(len(cx)) if scale is None else np.ascontiguousarray(scale, dtype=np.float64)
    m, phi0 = _feature_table(lm)
    thetas = np.asarray(th, dtype=np.float64)[:, None] + (np.arange(2 * n_steps + 1) - n_steps)[None, :] \
        * lm.angle_step  # (C, A)
    return sk.track_batch(np.ascontiguousarray(resp), m, phi0, np.ascontiguousarray(cx, dtype=np.int64),
                          np.ascontiguousarray(cy, dtype=np.int64), np.cos(thetas), np.sin(thetas), thetas, k_s,
                          int(reach), BIN_W)


def _feature_table(lm: LevelModel) -> tuple[F64, F64]:
    """The level's feature offsets (F, 2) and their normals' angles (rad), computed once per model."""
    key = (id(lm.points), id(lm.normals), id(lm.features))
    cached = lm.__dict__.get("_feature_table")
    if cached is None or cached[0] != key:
        m = np.ascontiguousarray(lm.points[lm.features])
        n = lm.normals[lm.features]
        cached = (key, (m, np.ascontiguousarray(np.arctan2(n[:, 1], n[:, 0]))))
        lm.__dict__["_feature_table"] = cached
    return cached[1]
