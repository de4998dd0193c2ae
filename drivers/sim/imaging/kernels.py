"""Compiled inner loops of the renderer (numba): ray-plane hits, sub-pixel rays, edge pixels.

Each loop fuses what would be a dozen full-image numpy passes into one, and compacts the rays
that hit a plane so that the plane's reflectance (a numpy function) is evaluated on those only.
Compiled once and cached on disk beside this module (``cache=True``); the renderer's
``render_scene`` is the public entry, these are its private pieces.

Conventions: ``field`` is the (H, W, 2) ray field (``[x, y, 1]`` rays, float64); a plane is the
homography ``H`` from rays to homogeneous object coordinates (row 2 the plane normal) and
``d = n . t`` (hit depth ``d / (n . ray)``); ``depth``, ``which`` and ``value`` are flat arrays
over the rays being shaded (pixels, or sub-pixel rays ``e * n * n + j * n + i``).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(cache=True, nogil=True)
def hit_pixels(field: NDArray[np.float64], r0: int, r1: int, c0: int, c1: int, H: NDArray[np.float64],
               d: float, index: int, depth: NDArray[np.float64], which: NDArray[np.int32],
               ox: NDArray[np.float64], oy: NDArray[np.float64], lam: NDArray[np.float64],
               flat: NDArray[np.int64]) -> int:  # pragma: no cover - compiled
    """Pixel-centre rays of the window that hit the plane in front of ``depth`` (ties: the lower
    object index wins); their object coordinates, depth and flat pixel index, compacted. Count."""
    width = field.shape[1]
    n = 0
    for r in range(r0, r1):
        for c in range(c0, c1):
            x = field[r, c, 0]
            y = field[r, c, 1]
            w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
            if w == 0.0:
                continue
            lm = d / w
            k = r * width + c
            if lm > 0.0 and (lm < depth[k] or (lm == depth[k] and which[k] > index)):
                ox[n] = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
                oy[n] = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
                lam[n] = lm
                flat[n] = k
                n += 1
    return n


@njit(cache=True, nogil=True)
def local_field(field: NDArray[np.float64], r: int, c: int) -> tuple[float, float, float, float, float, float]:
    """The ray field at pixel (r, c) and its derivatives along the columns and the rows (central
    differences, one-sided at the image border): a sub-ray at offset (ou, ov) px is
    ``(bx + ou dux + ov dvx, by + ou duy + ov dvy)``."""
    h, w_img = field.shape[0], field.shape[1]
    cl, cr = max(c - 1, 0), min(c + 1, w_img - 1)
    ru, rd = max(r - 1, 0), min(r + 1, h - 1)
    dux = (field[r, cr, 0] - field[r, cl, 0]) / (cr - cl)
    duy = (field[r, cr, 1] - field[r, cl, 1]) / (cr - cl)
    dvx = (field[rd, c, 0] - field[ru, c, 0]) / (rd - ru)
    dvy = (field[rd, c, 1] - field[ru, c, 1]) / (rd - ru)
    return field[r, c, 0], field[r, c, 1], dux, duy, dvx, dvy


@njit(cache=True, nogil=True)
def hit_subrays(field: NDArray[np.float64], rows: NDArray[np.int64], cols: NDArray[np.int64],
                only: NDArray[np.int64], nsub: int, r0: int, r1: int, c0: int, c1: int,
                H: NDArray[np.float64], d: float, index: int, depth: NDArray[np.float64],
                which: NDArray[np.int32], ox: NDArray[np.float64], oy: NDArray[np.float64],
                lam: NDArray[np.float64], flat: NDArray[np.int64]) -> int:  # pragma: no cover
    """As ``hit_pixels`` for the ``nsub x nsub`` sub-pixel rays of the listed pixels.

    A pixel takes part when ``only`` names this plane, or when it is -2 (several objects
    around it) and the pixel is inside the plane's window. Sub-rays are linear in the ray field
    (central differences, one-sided at the image border).
    """
    n2 = nsub * nsub
    n = 0
    for e in range(rows.size):
        r = rows[e]
        c = cols[e]
        if only[e] != index and not (only[e] == -2 and r0 <= r < r1 and c0 <= c < c1):
            continue
        bx, by, dux, duy, dvx, dvy = local_field(field, r, c)
        for j in range(nsub):
            ov = (j + 0.5) / nsub - 0.5
            for i in range(nsub):
                ou = (i + 0.5) / nsub - 0.5
                x = bx + ou * dux + ov * dvx
                y = by + ou * duy + ov * dvy
                w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
                if w == 0.0:
                    continue
                lm = d / w
                k = e * n2 + j * nsub + i
                if lm > 0.0 and (lm < depth[k] or (lm == depth[k] and which[k] > index)):
                    ox[n] = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
                    oy[n] = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
                    lam[n] = lm
                    flat[n] = k
                    n += 1
    return n


@njit(cache=True, nogil=True)
def take_hits(n: int, refl: NDArray[np.float64], lam: NDArray[np.float64], flat: NDArray[np.int64], index: int,
              value: NDArray[np.float64], depth: NDArray[np.float64],
              which: NDArray[np.int32]) -> None:  # pragma: no cover - compiled
    """Store the hits whose reflectance is defined (not NaN: the object is there)."""
    for i in range(n):
        v = refl[i]
        if np.isfinite(v):
            k = flat[i]
            value[k] = v
            depth[k] = lam[i]
            which[k] = index


@njit(cache=True, nogil=True)
def edge_pixels(value: NDArray[np.float64], which: NDArray[np.int32], r0: int, r1: int
                ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:  # pragma: no cover
    """Pixels of rows ``r0:r1`` whose value or object differs from one of their 8 neighbours
    (inside the image), and the one object their 3x3 neighbourhood sees (-1 background, -2 several).

    Each neighbouring pair is compared once (right, down-left, down, down-right) and marks both;
    the rows just outside the band are read, never written, so bands can run in parallel. The
    comparisons go into a row buffer first, so that each loop is a plain vectorisable one.
    """
    h, w = value.shape
    lo_r = max(r0 - 1, 0)
    hi_r = min(r1 + 1, h)
    mark = np.zeros((hi_r - lo_r, w), np.uint8)  # bit 0: edge; bit 1: more than one object around
    tmp = np.empty(w, np.uint8)
    for r in range(lo_r, hi_r):
        a = r - lo_r
        vr = value[r]
        wr = which[r]
        for c in range(w - 1):
            tmp[c] = np.uint8(3 if wr[c] != wr[c + 1] else (1 if vr[c] != vr[c + 1] else 0))
        for c in range(w - 1):
            mark[a, c] |= tmp[c]
        for c in range(w - 1):
            mark[a, c + 1] |= tmp[c]
        if r + 1 >= hi_r:
            continue
        vd = value[r + 1]
        wd = which[r + 1]
        for dc in (-1, 0, 1):
            lo = max(0, -dc)
            hi = min(w, w - dc)
            for c in range(lo, hi):
                tmp[c] = np.uint8(3 if wr[c] != wd[c + dc] else (1 if vr[c] != vd[c + dc] else 0))
            for c in range(lo, hi):
                mark[a, c] |= tmp[c]
            for c in range(lo, hi):
                mark[a + 1, c + dc] |= tmp[c]
    n = 0
    for r in range(r0, r1):
        for c in range(w):
            if mark[r - lo_r, c]:
                n += 1
    rows = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    only = np.empty(n, np.int64)
    n = 0
    for r in range(r0, r1):
        for c in range(w):
            m = mark[r - lo_r, c]
            if m:
                rows[n] = r
                cols[n] = c
                only[n] = -2 if m & 2 else which[r, c]
                n += 1
    return rows, cols, only


@njit(cache=True, nogil=True)
def levels(reflectance: NDArray[np.float64], black: float, scale: float, gain: NDArray[np.float32],
           out: NDArray[np.float32]) -> None:  # pragma: no cover - compiled
    """``out = float32(black + scale * reflectance) * gain`` (grey levels, DN); ``gain`` is a
    light map (H, W), a row ramp (1, W), or empty (no gain). One pass instead of numpy's four."""
    h, w = reflectance.shape
    for r in range(h):
        gr = min(r, gain.shape[0] - 1)
        for c in range(w):
            v = np.float32(black + scale * reflectance[r, c])
            out[r, c] = v * gain[gr, c] if gain.shape[0] else v


@njit(cache=True, nogil=True)
def encode(img: NDArray[np.float32], noise: NDArray[np.float32],
           out: NDArray[np.uint8]) -> None:  # pragma: no cover - compiled
    """``out = uint8(clip(rint(img + noise), 0, 255))`` in float32 (``noise`` empty: none)."""
    h, w = img.shape
    for r in range(h):
        for c in range(w):
            v = img[r, c] + noise[r, c] if noise.shape[0] else img[r, c]
            v = np.rint(v)
            out[r, c] = np.uint8(min(max(v, np.float32(0.0)), np.float32(255.0)))


@njit(cache=True, nogil=True)
def shot_noise(img: NDArray[np.float32], z: NDArray[np.float32], gain: np.float32, read2: np.float32,
               below: np.float32, out: NDArray[np.float32]) -> int:  # pragma: no cover - compiled
    """``out = s + z sqrt(s gain + read2)`` with ``s = max(img, 0)`` (DN, float32: the shot and
    read noise's Gaussian limit); the count of pixels with ``s < below`` (to be drawn Poisson)."""
    h, w = img.shape
    low = 0
    for r in range(h):
        for c in range(w):
            s = max(img[r, c], np.float32(0.0))
            out[r, c] = s + z[r, c] * np.sqrt(s * gain + read2)
            low += s < below
    return low
