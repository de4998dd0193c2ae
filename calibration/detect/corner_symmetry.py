"""Chessboard corner refinement by point symmetry, with a window sized by the local square.

A chessboard is point-symmetric about each of its corners: for the true corner ``q`` (image
pixels, pixel-centre convention) ``I(q + x) = I(q - x)`` for every offset ``x`` inside the
corner's neighbourhood, whatever the angle between the board lines. Blur (any centred kernel:
lens, defocus, motion), gamma and any other grey-level mapping keep the symmetry. The
refinement finds ``q`` by Gauss-Newton on

    sum_x w(x) (I(q + x) - I(q - x))^2

over a window whose half size is ``SYMMETRY_WINDOW_SQUARES`` of the corner's *local* square (the
distance to its nearest grid neighbour, px), so every edge contributes a stretch of its length
rather than the few pixels next to the corner. Where the board lines run within a few degrees of
the pixel axes a small window sees each edge over only a couple of pixels and the quadratic
saddle fit (``chessboard.refine_saddle_converged``, ±3 px) errs 2-3x more (issue 26). On the
issue's defect-laden renders the corner RMS error went 0.052 -> 0.023 px (960x720, blur 0.7 px,
shot + read noise, gamma 1.1, JPEG 92) and 0.029 -> 0.017 px with the real-defects scene's
imaging (bench/intrinsics_heldout.py measures the calibrations that follow).

Weights are Gaussian with sigma ``0.7 x`` the half window; the image is smoothed lightly first
(``SMOOTH_SIGMA_PX``) so bilinear sampling does not add its own ripple, and sampled with exact
bilinear weights (``calibration.detect.sampling``, ``exact=True``: ``cv2.remap`` rounds positions to 1/32 px,
a bias of up to 0.016 px on every sample of a corner). The window is also kept
inside the image (a replicated border is not symmetric).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.sampling import sample_bilinear

FloatArray = NDArray[np.float64]

SYMMETRY_WINDOW_SQUARES = 0.5
"""Half window (as a fraction of the local square size): corner RMS 0.028 / 0.025 / 0.023 px at
0.3 / 0.4 / 0.5 on the issue-26 renders (0.018 / 0.018 / 0.017 with the real-defects scene's
imaging); up to half a square the window sees only the four squares that meet at the corner."""
MIN_HALF_WINDOW_PX = 3
MAX_HALF_WINDOW_PX = 25
"""Cap for very large squares (the gain flattens beyond ~15 px, the cost grows with its square)."""
SMOOTH_SIGMA_PX = 0.7
WEIGHT_SIGMA_FRACTION = 0.7
CONVERGED_PX = 0.05
"""A refinement has converged when its last step is shorter than this (px)."""
MIN_CONDITION = 0.02
"""The normal matrix's smaller / larger eigenvalue below this: no corner (an edge or flat area)."""


def local_square_px(grid_uv: FloatArray) -> FloatArray:
    """(rows, cols) distance (px) from each corner of a (rows, cols, 2) grid to its nearest grid
    neighbour: the local square size."""
    rows, cols = grid_uv.shape[:2]
    out = np.full((rows, cols), np.inf)
    dx = np.linalg.norm(np.diff(grid_uv, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(grid_uv, axis=0), axis=2)
    out[:, :-1] = np.minimum(out[:, :-1], dx)
    out[:, 1:] = np.minimum(out[:, 1:], dx)
    out[:-1] = np.minimum(out[:-1], dy)
    out[1:] = np.minimum(out[1:], dy)
    return out


def half_windows_px(grey_shape: tuple[int, ...], uv: FloatArray, square_px: FloatArray) -> NDArray[np.int64]:
    """(N,) half window (px) per corner: ``SYMMETRY_WINDOW_SQUARES`` of its square, within
    [MIN_HALF_WINDOW_PX, MAX_HALF_WINDOW_PX] and inside the image."""
    h, w = grey_shape[:2]
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    hw = np.floor(SYMMETRY_WINDOW_SQUARES * np.asarray(square_px, dtype=np.float64).reshape(-1))
    border = np.floor(np.min(np.column_stack([pts[:, 0], pts[:, 1], w - 1 - pts[:, 0], h - 1 - pts[:, 1]]),
                             axis=1)) - 1
    hw = np.minimum(np.minimum(hw, MAX_HALF_WINDOW_PX), border)
    return np.maximum(np.nan_to_num(hw, nan=MIN_HALF_WINDOW_PX), MIN_HALF_WINDOW_PX).astype(np.int64)


def refine_symmetric(grey: NDArray[np.uint8], uv: FloatArray, half_window_px: int | NDArray[np.int64],
                     iterations: int = 8) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Refine chessboard corners ``uv`` (N, 2, px) to their centres of point symmetry.

    ``half_window_px``: one half window for all corners or one per corner (px). Each step is at
    most 1 px long. Returns the refined (N, 2) corners and a mask of those that converged (last
    step below ``CONVERGED_PX``, a well-conditioned normal matrix: a corner, not an edge)."""
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), SMOOTH_SIGMA_PX)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2).copy()
    hws = np.broadcast_to(np.asarray(half_window_px, dtype=np.int64), (len(pts),))
    converged = np.zeros(len(pts), dtype=bool)
    for hw in np.unique(hws):
        sel = np.flatnonzero(hws == hw)
        pts[sel], converged[sel] = _refine_group(img, gx, gy, pts[sel], int(hw), iterations)
    return pts, converged


def _refine_group(img: NDArray[np.float32], gx: NDArray[np.float32], gy: NDArray[np.float32], pts: FloatArray,
                  hw: int, iterations: int) -> tuple[FloatArray, NDArray[np.bool_]]:
    r = np.arange(-hw, hw + 1, dtype=np.float64)
    du, dv = (a.ravel() for a in np.meshgrid(r, r))
    half = (dv > 0) | ((dv == 0) & (du > 0))          # one offset of each symmetric pair
    du, dv = du[half], dv[half]
    w = np.exp(-(du**2 + dv**2) / (2 * (WEIGHT_SIGMA_FRACTION * hw) ** 2))
    out = pts.copy()
    length = np.full(len(out), np.inf)
    cond = np.zeros(len(out))

    def sample(a: NDArray[np.float32], sign: float) -> FloatArray:
        return sample_bilinear(a, out[:, 0:1] + sign * du[None, :], out[:, 1:2] + sign * dv[None, :],
                               exact=True)

    for _ in range(iterations):
        res = sample(img, 1.0) - sample(img, -1.0)
        jx = sample(gx, 1.0) - sample(gx, -1.0)
        jy = sample(gy, 1.0) - sample(gy, -1.0)
        a11, a12, a22 = (w * jx * jx).sum(1), (w * jx * jy).sum(1), (w * jy * jy).sum(1)
        b1, b2 = (w * jx * res).sum(1), (w * jy * res).sum(1)
        det = a11 * a22 - a12**2
        tr = a11 + a22
        disc = np.sqrt(np.maximum(tr**2 / 4 - det, 0.0))
        cond = np.where(tr > 0, (tr / 2 - disc) / np.maximum(tr / 2 + disc, 1e-300), 0.0)
        ok = (det > 0) & (cond > MIN_CONDITION)
        safe = np.where(ok, det, 1.0)
        step = np.column_stack([-(a22 * b1 - a12 * b2) / safe, -(a11 * b2 - a12 * b1) / safe])
        step[~ok] = 0.0
        length = np.linalg.norm(step, axis=1)
        long = length > 1.0
        step[long] /= length[long, None]
        out += step
        if np.all(length[ok] < 1e-4):
            break
    return out, (cond > MIN_CONDITION) & (length < CONVERGED_PX)
