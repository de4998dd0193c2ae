"""The patch fit's inner loop, compiled (numba): one pass over the samples builds the Gauss-Newton
system of ``patch.fit`` and, on the last pass, the per-block systems of its jackknife.

Parameters, in this order: ``t`` (2), ``A`` (4, row-major), ``v`` (2) of the plane homography
``q = (A p + t) / (1 + v.p)``, then the light's gain ``a`` and offset ``b`` (``T ~ a I(q) + b``).
Units: pixels of the image crop; grey levels.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from vision.image import F64

NP = 10
"""Parameters of the fit."""


@njit(cache=True)
def _bil(img: NDArray[np.float32], x: float, y: float) -> float:
    h, w = img.shape
    x = min(max(x, 0.0), w - 1.001)
    y = min(max(y, 0.0), h - 1.001)
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] + (img[y0, x0 + 1] - img[y0, x0]) * fx
    bot = img[y0 + 1, x0] + (img[y0 + 1, x0 + 1] - img[y0 + 1, x0]) * fx
    return top + (bot - top) * fy


@njit(cache=True)
def normal_equations(crop: NDArray[np.float32], gx: NDArray[np.float32], gy: NDArray[np.float32], pts: F64,
                     T: F64, block: NDArray[np.int64], nblocks: int, par: F64, sd: float, tukey_c: float,
                     blocks: bool) -> tuple[F64, F64, F64, F64, F64, NDArray[np.bool_]]:
    """``H`` (10, 10), ``g`` (10) of the Tukey-weighted least squares at ``par`` (residual spread
    ``sd``; ``sd <= 0``: weights 1), per-block ``Hb`` (nblocks, 10, 10) and ``gb`` when ``blocks``,
    the residuals ``r`` and which samples fell inside the crop."""
    n = pts.shape[0]
    h, w = crop.shape
    t0, t1, a00, a01, a10, a11, v0, v1, ga, gb_ = par[0], par[1], par[2], par[3], par[4], par[5], par[6], \
        par[7], par[8], par[9]
    H = np.zeros((NP, NP))
    g = np.zeros(NP)
    nb = nblocks if blocks else 1
    Hb = np.zeros((nb, NP, NP))
    Gb = np.zeros((nb, NP))
    r = np.zeros(n)
    inside = np.zeros(n, np.bool_)
    J = np.empty(NP)
    for i in range(n):
        px, py = pts[i, 0], pts[i, 1]
        wp = 1.0 + v0 * px + v1 * py
        qx = (a00 * px + a01 * py + t0) / wp
        qy = (a10 * px + a11 * py + t1) / wp
        if not (qx >= 1.0 and qy >= 1.0 and qx <= w - 2.0 and qy <= h - 2.0):
            continue
        inside[i] = True
        I = _bil(crop, qx, qy)
        res = ga * I + gb_ - T[i]
        r[i] = res
        if sd > 0:
            u2 = (res / (tukey_c * sd)) ** 2
            if u2 >= 1.0:
                continue
            wt = (1.0 - u2) ** 2
        else:
            wt = 1.0
        ax = ga * _bil(gx, qx, qy) / wp
        ay = ga * _bil(gy, qx, qy) / wp
        aq = ax * qx + ay * qy
        J[0], J[1] = ax, ay
        J[2], J[3], J[4], J[5] = ax * px, ax * py, ay * px, ay * py
        J[6], J[7] = -aq * px, -aq * py
        J[8], J[9] = I, 1.0
        k = block[i] if blocks else 0
        for p in range(NP):
            wj = wt * J[p]
            g[p] += wj * res
            if blocks:
                Gb[k, p] += wj * res
            for q in range(p, NP):
                H[p, q] += wj * J[q]
                if blocks:
                    Hb[k, p, q] += wj * J[q]
    for p in range(NP):
        for q in range(p):
            H[p, q] = H[q, p]
            for k in range(nb if blocks else 0):
                Hb[k, p, q] = Hb[k, q, p]
    return H, g, Hb, Gb, r, inside


@njit(cache=True)
def weighted_rss(r: F64, inside: NDArray[np.bool_], sd: float, tukey_c: float) -> tuple[float, float, int]:
    """Sum of Tukey weights, of weighted squared residuals, and the samples weighted (for the
    textbook covariance)."""
    sw, swr, cnt = 0.0, 0.0, 0
    for i in range(r.shape[0]):
        if not inside[i]:
            continue
        u2 = (r[i] / (tukey_c * sd)) ** 2 if sd > 0 else 0.0
        if u2 < 1.0:
            wt = (1.0 - u2) ** 2
            sw += wt
            swr += wt * r[i] * r[i]
            cnt += 1
    return sw, swr, cnt
