"""Compiled shading of the calibration targets' printed patterns (numba), for the renderer.

``calibration.targets`` defines each pattern by its ``reflectance(x, y)`` (numpy, object frame,
metres). On a frame of the virtual cell those numpy passes were the renderer's largest cost, so
for the targets whose patterns are simple geometry (circle plate, chessboard, circle grid) this
module evaluates the *same arithmetic* in one compiled loop that also stores the hits (reflectance
and ``take_hits`` fused). The results are bit-identical to the numpy methods:
``tests/calibration/test_render_patterns.py`` checks every pattern on random points and on points
exactly on its edges, and whole frames against the numpy path. ChArUco (marker bitmaps) and any
other reflectance stay on the numpy path.

``shader_for(reflectance)`` returns a ``Shader`` for a target's bound ``reflectance`` method (None
for anything else, including subclasses that override it). It shades compacted hits (as
``render_kernels.take_hits`` does after a numpy reflectance), a plain pixel pass (ray, hit and
pattern in one loop), and the edge pixels that see this pattern alone (sub-rays, pattern and numpy's
pairwise mean in one loop, vectorised for the circle plate).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from calibration.targets import MM, Chessboard, CircleGrid, CirclePlate
from drivers.sim.imaging.kernels import local_field

F64 = NDArray[np.float64]
# Every loop here is compiled with numpy's error model: a ray parallel to a plane (w == 0) divides
# by zero to +-inf or NaN, which the hit tests reject, instead of raising (numba's Python model).


CIRCLE_PLATE, CHESSBOARD, CIRCLE_GRID = 0, 1, 2

# The small helpers below are plain compiled functions, which LLVM inlines into their callers as it
# sees fit (the frames are bit for bit the same); numba's ``inline="always"`` typed and compiled each
# again inside every caller: about 3 s more CPU for the renderer's cold compile (13.4 s against 9-11 s).


@njit(cache=True, nogil=True, error_model="numpy")
def _plate(x: float, y: float, g: F64, cols: int, rows: int) -> float:  # pragma: no cover - compiled
    """``CirclePlate.reflectance`` at ``(x, y)``, NaN off the plate. Branch-free (bitwise &, |): at
    the edge pixels being supersampled the outcome flips from one sub-ray to the next, and
    mispredicted branches cost more than the spare arithmetic; it also lets LLVM vectorise."""
    on = (x >= g[11]) & (x <= g[13]) & (y >= g[12]) & (y <= g[14])  # _on_plate, extent_m
    x0, y0, x1, y1 = g[4], g[5], g[6], g[7]  # inner edge of the frame
    frame = (x >= g[0]) & (x <= g[2]) & (y >= g[1]) & (y <= g[3]) & ~((x > x0) & (x < x1) & (y > y0) & (y < y1))
    triangle = (x >= x0) & (y >= y0) & ((x - x0) + (y - y0) <= g[8])
    p = g[9]
    c = min(max(np.rint(x / p), 0.0), cols - 1.0)  # nearest mark
    r = min(max(np.rint(y / p), 0.0), rows - 1.0)
    dx = x - c * p
    dy = y - r * p
    black = frame | triangle | (dx * dx + dy * dy <= g[10])
    v = 1.0 - np.float64(black)
    return v if on else np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _value(kind: int, x: float, y: float, g: F64, centres: F64, cols: int, rows: int
           ) -> float:  # pragma: no cover - compiled
    """The pattern's reflectance at object point ``(x, y)`` (m), NaN off the plate: the same
    arithmetic, in the same order, as the target's numpy ``reflectance``."""
    if kind == CIRCLE_PLATE:
        return _plate(x, y, g, cols, rows)
    if not (x >= g[1] and x <= g[3] and y >= g[2] and y <= g[4]):
        return np.nan
    if kind == CHESSBOARD:
        i = np.floor(x / g[0])
        j = np.floor(y / g[0])
        on = i >= -1 and i <= cols - 1 and j >= -1 and j <= rows - 1
        return 0.0 if on and ((i + j) % 2) == 0 else 1.0
    for m in range(centres.shape[0]):  # CIRCLE_GRID
        dx = x - centres[m, 0]
        dy = y - centres[m, 1]
        if dx * dx + dy * dy <= g[0]:
            return 0.0
    return 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def shade_hits(kind: int, g: F64, centres: F64, cols: int, rows: int, n: int, ox: F64, oy: F64, lam: F64,
               flat: NDArray[np.int64], index: int, value: F64, depth: F64,
               which: NDArray[np.int32]) -> None:  # pragma: no cover - compiled
    """The pattern's reflectance at ``n`` compacted hits, stored where defined (``take_hits``)."""
    for t in range(n):
        v = _value(kind, ox[t], oy[t], g, centres, cols, rows)
        if np.isfinite(v):
            k = flat[t]
            value[k] = v
            depth[k] = lam[t]
            which[k] = index


@njit(cache=True, nogil=True, error_model="numpy")
def shade_pixels(kind: int, g: F64, centres: F64, cols: int, rows: int, field: F64, r0: int, r1: int, c0: int,
                 c1: int, H: F64, d: float, index: int, value: F64, depth: F64,
                 which: NDArray[np.int32]) -> None:  # pragma: no cover - compiled
    """``render_kernels.hit_pixels`` and ``shade_hits`` in one pass (no compacted hits): per row, a
    branch-free loop (vectorised for the circle plate) computes every ray's depth and pattern
    value, then a plain loop stores those in front (``w == 0`` gives a depth of +-inf or NaN,
    which never is)."""
    width = field.shape[1]
    n = c1 - c0
    lam = np.empty(n)
    val = np.empty(n)
    for r in range(r0, r1):
        if kind == CIRCLE_PLATE:
            for t in range(n):
                ox, oy, lm = _ray(field[r, c0 + t, 0], field[r, c0 + t, 1], H, d)
                lam[t] = lm
                val[t] = _plate(ox, oy, g, cols, rows)
        else:
            for t in range(n):
                ox, oy, lm = _ray(field[r, c0 + t, 0], field[r, c0 + t, 1], H, d)
                lam[t] = lm
                val[t] = _value(kind, ox, oy, g, centres, cols, rows)
        for t in range(n):
            k = r * width + c0 + t
            lm = lam[t]
            v = val[t]
            if lm > 0.0 and (lm < depth[k] or (lm == depth[k] and which[k] > index)) and v == v:
                value[k] = v
                depth[k] = lm
                which[k] = index


@njit(cache=True, nogil=True, error_model="numpy")
def _ray(x: float, y: float, H: F64, d: float) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """Ray ``[x, y, 1]``'s hit on the plane: object x, y (m) and depth, as ``hit_pixels`` forms them."""
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w, d / w


@njit(cache=True, nogil=True, error_model="numpy")
def _mean(a: F64, n: int) -> float:  # pragma: no cover - compiled
    """``numpy.mean`` of ``a[:n]`` bit for bit: numpy's pairwise sum (8 partial sums up to 128)."""
    if n < 8:
        s = 0.0
        for i in range(n):
            s += a[i]
        return s / n
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - (n % 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        s += a[i]
        i += 1
    return s / n


@njit(cache=True, nogil=True, error_model="numpy")
def supersample_alone(kind: int, g: F64, centres: F64, cols: int, rows: int, field: F64,
                      pix_rows: NDArray[np.int64], pix_cols: NDArray[np.int64], nsub: int, H: F64, d: float,
                      background: float, out: F64) -> None:  # pragma: no cover - compiled
    """Box-filtered value of pixels that see this plane alone (nothing else in their 3x3
    neighbourhood), from ``nsub x nsub`` sub-rays each: ray, hit, pattern and mean in one loop.

    The same sub-rays (``render_kernels.hit_subrays``), the same hit test against an empty
    pixel, and numpy's mean: bit-identical to the generic path, without its buffers.
    """
    n2 = nsub * nsub
    if n2 > 128:  # beyond numpy's pairwise block: _mean would differ from it
        raise ValueError("supersample_alone: at most 11 x 11 sub-rays")
    ou = np.empty(n2)  # sub-ray offsets (px), sub-ray j * nsub + i
    ov = np.empty(n2)
    for j in range(nsub):
        for i in range(nsub):
            ou[j * nsub + i] = (i + 0.5) / nsub - 0.5
            ov[j * nsub + i] = (j + 0.5) / nsub - 0.5
    sub = np.empty(n2)
    for e in range(pix_rows.size):
        r = pix_rows[e]
        c = pix_cols[e]
        bx, by, dux, duy, dvx, dvy = local_field(field, r, c)
        # Flat, branch-free loops over the sub-rays: a ray misses when its depth is not in (0, inf)
        # (w == 0 included) or the pattern is not there (NaN).
        # The circle plate's loop apart: the pattern switch inside a loop stops the vectoriser.
        if kind == CIRCLE_PLATE:
            for t in range(n2):
                ox, oy, front = _subray(bx, by, ou[t], ov[t], dux, duy, dvx, dvy, H, d)
                v = _plate(ox, oy, g, cols, rows)
                sub[t] = v if front & (v == v) else background
        else:
            for t in range(n2):
                ox, oy, front = _subray(bx, by, ou[t], ov[t], dux, duy, dvx, dvy, H, d)
                v = _value(kind, ox, oy, g, centres, cols, rows)
                sub[t] = v if front & (v == v) else background
        out[e] = _mean(sub, n2)


@njit(cache=True, nogil=True, error_model="numpy")
def _subray(bx: float, by: float, ou: float, ov: float, dux: float, duy: float, dvx: float, dvy: float, H: F64,
            d: float) -> tuple[float, float, bool]:  # pragma: no cover - compiled
    """A sub-ray's hit on the plane (object x, y in m) and whether it is in front of the camera
    (depth in (0, inf), so ``w == 0`` misses): ``render_kernels.hit_subrays``' arithmetic."""
    x = bx + ou * dux + ov * dvx
    y = by + ou * duy + ov * dvy
    ww = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    lm = d / ww
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / ww, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / ww, (lm > 0.0) & (
        lm < np.inf)


@dataclass(frozen=True)
class Shader:
    """A target pattern in compiled form: its kind and constants."""

    kind: int
    g: F64
    centres: F64
    cols: int
    rows: int

    def __call__(self, n: int, ox: F64, oy: F64, lam: F64, flat: NDArray[np.int64], index: int, value: F64,
                 depth: F64, which: NDArray[np.int32]) -> None:
        shade_hits(self.kind, self.g, self.centres, self.cols, self.rows, n, ox, oy, lam, flat, index, value,
                   depth, which)

    def shade_pixels(self, field: F64, r0: int, r1: int, c0: int, c1: int, H: F64, d: float, index: int,
                     value: F64, depth: F64, which: NDArray[np.int32]) -> None:
        shade_pixels(self.kind, self.g, self.centres, self.cols, self.rows, field, r0, r1, c0, c1, H, d, index,
                     value, depth, which)

    def supersample_alone(self, field: F64, rows: NDArray[np.int64], cols: NDArray[np.int64], nsub: int,
                          H: F64, d: float, background: float, out: F64) -> None:
        supersample_alone(self.kind, self.g, self.centres, self.cols, self.rows, field, rows, cols, nsub, H, d,
                          background, out)


def shader_for(reflectance: Callable[[F64, F64], F64]) -> Shader | None:
    """The compiled shader of a target's own ``reflectance`` method, or None (numpy path)."""
    target = getattr(reflectance, "__self__", None)
    func = getattr(reflectance, "__func__", None)
    none = np.zeros((0, 2))
    if isinstance(target, CirclePlate) and func is CirclePlate.reflectance:
        p = target.pitch_m
        x0, y0, x1, y1 = target.frame_inner_m()
        w = p / 2
        # The constants exactly as the numpy method forms them (Python floats), so the bits agree.
        g = np.array([x0 - w, y0 - w, x1 + w, y1 + w, x0, y0, x1, y1, p / 2, p, target.radius_m**2,
                      *target.extent_m()], dtype=np.float64)
        return Shader(CIRCLE_PLATE, g, none, int(target.cols), int(target.rows))
    if isinstance(target, Chessboard) and func is Chessboard.reflectance:
        g = np.array([target.square_m, *target.extent_m()], dtype=np.float64)
        return Shader(CHESSBOARD, g, none, int(target.cols), int(target.rows))
    if isinstance(target, CircleGrid) and func is CircleGrid.reflectance:
        g = np.array([(target.diameter_mm * MM / 2) ** 2, *target.extent_m()], dtype=np.float64)
        centres = np.ascontiguousarray(target.points().xyz_m[:, :2], dtype=np.float64)
        return Shader(CIRCLE_GRID, g, centres, 0, 0)
    return None
