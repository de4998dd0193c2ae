"""Chessboard inner corners: OpenCV's ``findChessboardCornersSB`` plus our id convention and checks.

Ids are ``row * cols + col`` in the target frame (docs/cli.md). OpenCV returns the
corners row by row but may start at any end of the board; we re-order them:

1. the grid must be right-handed as seen by the camera (target x to y turns clockwise on
   screen, as for any target seen from its printed side); for square boards this also fixes
   OpenCV's possible transposition;
2. if ``cols + rows`` is odd, the board is not symmetric under a half turn: the printed square
   diagonally outside corner 0 is black (``calibration.targets.Chessboard``), the one outside the
   last corner white, and we read which end is which from the image;
3. if ``cols + rows`` is even, the board looks the same after a half turn and no image can tell
   the two orders apart: we pick the one whose x axis points rightwards on screen (angle in
   (-90°, 90°]), a fixed convention rather than a fact about the board.

A board with an inner corner closer to the image border than ``MIN_BORDER_SQUARES`` of a square
(a cropped board) is reported not found: that corner's neighbourhood is cut off, so it cannot be
localized reliably (OpenCV's sector detector still "finds" such boards, e.g. Udacity's
calibration4.jpg).

Sub-pixel accuracy, in two steps of our own:

1. a saddle-point fit (``refine_saddle_converged``: a weighted quadratic surface fitted to the
   lightly smoothed image in a ±3 px window, moved to its saddle point, iterated) brings
   OpenCV's sector-detector positions (1-1.4 px off on blurred outer corners) close;
2. a point-symmetry refinement (``calibration.detect.corner_symmetry``) over a window of half
   each corner's own square, so each edge contributes a stretch of its length: the ±3 px saddle
   window saw too little of edges running near the pixel axes (issue 26: 0.08 px error there).

bench/detection.py and bench/intrinsics_heldout.py measure them against ``findChessboardCornersSB``
with ``CALIB_CB_ACCURACY``. Both steps are skipped where squares are too small, and a corner
whose refinement does not converge (or would move it more than ``SADDLE_MAX_MOVE_PX`` from
OpenCV's position) keeps the previous position. Each corner carries its 1-sigma uncertainty
from the image structure and noise in its refinement window (``calibration.detect.precision``).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.corner_symmetry import (
    WEIGHT_SIGMA_FRACTION,
    half_windows_px,
    local_square_px,
    refine_symmetric,
)
from calibration.detect.precision import CORNER_WINDOW_SIGMA_PX, gradient_sigma_px
from calibration.detect.sampling import sample_bilinear
from calibration.observations import Detection
from calibration.targets import Chessboard

FloatArray = NDArray[np.float64]

SADDLE_HALF_WINDOW = 3
"""Half size (px) of the window of our saddle-point refinement."""

MIN_BORDER_SQUARES = 0.2
"""A corner closer to the image border than this fraction of its square has lost the part of the
adjoining squares that sub-pixel refinement looks at: the board is reported cropped."""


FIND_PASSES = (0, cv2.CALIB_CB_EXHAUSTIVE, cv2.CALIB_CB_ACCURACY)
"""``findChessboardCornersSB`` flags tried in turn until one finds the board."""


def find_corners_opencv(grey: NDArray[np.uint8], cols: int, rows: int, passes: tuple[int, ...] = FIND_PASSES
                        ) -> FloatArray | None:
    """OpenCV's sector-based detector; a fast pass first, then the exhaustive one, then one on the
    image upsampled (``CALIB_CB_ACCURACY``). (rows, cols, 2) or None.

    The first two passes run without ``CALIB_CB_ACCURACY``: our refinement reaches the same accuracy
    from the plain result at a quarter of the time (measured with bench/detection.py's scenes). The
    upsampled pass is a fallback only (it costs a board-less image one more pass): it finds boards the
    other two miss on blurred, low-contrast real images (3 of OpenCV's 26 stereo sample views:
    left04, left05, right01), whose corners our refinement then places as any other.
    """
    for flags in passes:
        ok, corners = cv2.findChessboardCornersSB(grey, (cols, rows), flags=flags)
        if ok and corners is not None:
            return np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    return None


def _handedness(G: FloatArray) -> float:
    ex = G[0, -1] - G[0, 0]
    ey = G[-1, 0] - G[0, 0]
    return float(ex[0] * ey[1] - ex[1] * ey[0])


def _sample(grey: NDArray[np.uint8], uv: FloatArray, radius: float) -> float:
    """Mean grey value in a small square around ``uv`` (NaN outside the image)."""
    h, w = grey.shape
    r = max(1, int(round(radius)))
    u, v = int(round(uv[0])), int(round(uv[1]))
    if u - r < 0 or v - r < 0 or u + r >= w or v + r >= h:
        return float("nan")
    return float(grey[v - r : v + r + 1, u - r : u + r + 1].mean())


def _parity_contrast(grey: NDArray[np.uint8], G: FloatArray) -> float:
    """Mean grey of the odd inner squares minus that of the even ones (positive: even are dark)."""
    centres = 0.5 * (G[:-1, :-1] + G[1:, 1:])
    step = float(np.median(np.linalg.norm(G[1:, 1:] - G[:-1, :-1], axis=2)))
    total = 0.0
    for r, c in np.ndindex(centres.shape[:2]):
        value = _sample(grey, centres[r, c], 0.12 * step)
        if np.isfinite(value):
            total += value if (r + c) % 2 else -value
    return total


def canonical_order(grey: NDArray[np.uint8], G: FloatArray, cols: int, rows: int, colour_cue: bool = True
                    ) -> FloatArray:
    """Re-order a (rows, cols, 2) corner grid into the target frame's order (see module docstring)."""
    cands = [G, G[::-1, ::-1], G[::-1, :], G[:, ::-1]]
    if cols == rows:
        T = G.transpose(1, 0, 2)
        cands += [T, T[::-1, ::-1], T[::-1, :], T[:, ::-1]]
    right = [c for c in cands if c.shape[:2] == (rows, cols) and _handedness(c) > 0]
    # right holds a grid and its half-turn (two each for square boards, equal up to a quarter turn).
    if colour_cue and (cols + rows) % 2 == 1:
        # Inner squares only (always inside the image): in the target frame the square between
        # corners (r, c) and (r+1, c+1) is black when r + c is even. The candidate whose even
        # squares are darker than its odd ones has the target's orientation.
        return max(right, key=lambda c: _parity_contrast(grey, c))
    if cols == rows:
        # Four quarter turns look alike on an even square board: x axis closest to screen-right.
        return min(right, key=lambda c: abs(np.arctan2(*(c[0, -1] - c[0, 0])[::-1])))
    ex = [c[0, -1] - c[0, 0] for c in right]
    for c, e in zip(right, ex, strict=True):
        ang = np.arctan2(e[1], e[0])
        if -np.pi / 2 < ang <= np.pi / 2:
            return c
    return right[0]


def border_margin_squares(G: FloatArray, width: int, height: int) -> float:
    """Smallest distance of an inner corner to the image border, in units of its local square size."""
    s = np.zeros(G.shape[:2])
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)
    s[:, :-1] = np.maximum(s[:, :-1], dx)
    s[:, 1:] = np.maximum(s[:, 1:], dx)
    s[:-1] = np.maximum(s[:-1], dy)
    s[1:] = np.maximum(s[1:], dy)
    P = G.reshape(-1, 2)
    dist = np.minimum.reduce([P[:, 0] + 0.5, P[:, 1] + 0.5, width - 0.5 - P[:, 0], height - 0.5 - P[:, 1]])
    return float((dist / np.maximum(s.ravel(), 1e-9)).min())


def refine_saddle(grey: NDArray[np.uint8], uv: FloatArray, half_window: int = 3, iterations: int = 3
                  ) -> FloatArray:
    """Our own saddle-point refinement: fit ``f = a u² + b uv + c v² + d u + e v + g`` to the lightly
    smoothed image in a small window and move to its stationary point (iterated).

    Kept for measurement (bench/detection.py); the detector uses ``refine_saddle_converged``.
    """
    return refine_saddle_converged(grey, uv, half_window, iterations)[0]


SADDLE_CONVERGED_PX = 0.05
"""A refinement has converged when its last step is shorter than this (px)."""
SADDLE_MAX_MOVE_PX = 2.0
"""A converged refinement may move a corner this far from OpenCV's position (within its window)."""


def refine_saddle_converged(grey: NDArray[np.uint8], uv: FloatArray, half_window: int = 3, iterations: int = 6
                            ) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``refine_saddle`` with each step limited to 1 px in length (not dropped: OpenCV's sector
    detector leaves blurred outer corners 1-1.4 px off, and a dropped first step left them
    there), and a mask of the corners whose refinement converged to a saddle (last step below
    ``SADDLE_CONVERGED_PX``)."""
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.0)
    h, w = img.shape
    out = np.asarray(uv, dtype=np.float64).copy()
    r = np.arange(-half_window, half_window + 1, dtype=np.float64)
    du_g, dv_g = np.meshgrid(r, r)
    du, dv = du_g.ravel(), dv_g.ravel()
    wts = np.exp(-(du**2 + dv**2) / (2 * (half_window * 0.7) ** 2))
    A = np.column_stack([du**2, du * dv, dv**2, du, dv, np.ones_like(du)]) * wts[:, None]
    pinv = np.linalg.pinv(A)
    converged = np.zeros(len(out), dtype=bool)
    for _ in range(iterations):
        vals = sample_bilinear(img, out[:, 0][:, None] + du[None, :], out[:, 1][:, None] + dv[None, :])
        coef = (vals * wts[None, :]) @ pinv.T
        a, b, c, d, e = coef[:, 0], coef[:, 1], coef[:, 2], coef[:, 3], coef[:, 4]
        det = 4 * a * c - b * b
        ok = det < 0  # a saddle
        step_u = np.where(ok, (b * e - 2 * c * d) / np.where(ok, det, 1.0), 0.0)
        step_v = np.where(ok, (b * d - 2 * a * e) / np.where(ok, det, 1.0), 0.0)
        step = np.column_stack([step_u, step_v])
        length = np.linalg.norm(step, axis=1)
        step[~np.isfinite(length)] = 0.0
        long = length > 1.0
        step[long] /= length[long, None]
        out += step
        converged = ok & (length < SADDLE_CONVERGED_PX)
    out[:, 0] = np.clip(out[:, 0], 0, w - 1)
    out[:, 1] = np.clip(out[:, 1], 0, h - 1)
    return out, converged


def detect_chessboard(grey: NDArray[np.uint8], target: Chessboard, image_name: str = "",
                      saddle_refinement: bool = True, symmetry_refinement: bool = True) -> Detection:
    """Inner corners of ``target`` in ``grey`` with target-frame ids, or a reason why not.

    ``symmetry_refinement=False``: the saddle fit alone (the detector before issue 26; benches)."""
    cols, rows = target.cols, target.rows
    h, w = grey.shape
    G = find_corners_opencv(grey, cols, rows)
    if G is None:
        return Detection(image_name, False, reason=f"no {cols}x{rows} chessboard found (board not fully "
                         "visible, too blurred, or a different size)")
    margin = border_margin_squares(G, w, h)
    if margin < MIN_BORDER_SQUARES:
        return Detection(image_name, False, reason=f"chessboard cropped by the image border (a corner lies "
                         f"{margin:.2f} squares from the edge, need {MIN_BORDER_SQUARES}); move the board into "
                         "the image")
    G = canonical_order(grey, G, cols, rows)
    uv = G.reshape(-1, 2)
    window_sigma = np.full(len(uv), CORNER_WINDOW_SIGMA_PX)
    if saddle_refinement:
        square_px = float(np.median(np.hypot(*np.diff(G, axis=1).reshape(-1, 2).T)))
        start = uv
        if square_px >= 4 * SADDLE_HALF_WINDOW:  # the window must see only this corner's four squares
            refined, converged = refine_saddle_converged(grey, uv, SADDLE_HALF_WINDOW)
            moved = np.hypot(*(refined - uv).T)
            uv = np.where((converged & (moved < SADDLE_MAX_MOVE_PX))[:, None], refined, uv)
        if square_px >= 4 * SADDLE_HALF_WINDOW and symmetry_refinement:
            # then the point-symmetry refinement over a window sized by each corner's own square
            hw = half_windows_px(grey.shape, uv, local_square_px(uv.reshape(G.shape)))
            sym, sym_ok = refine_symmetric(grey, uv, hw)
            use = sym_ok & (np.hypot(*(sym - start).T) < SADDLE_MAX_MOVE_PX)
            uv = np.where(use[:, None], sym, uv)
            window_sigma = np.where(use, WEIGHT_SIGMA_FRACTION * hw, CORNER_WINDOW_SIGMA_PX)
    ids = target.points().ids
    sigma = gradient_sigma_px(grey, uv, window_sigma)
    return Detection(image_name, True, ids=ids.copy(), uv=np.ascontiguousarray(uv, dtype=np.float64),
                     uv_sigma_px=sigma)
