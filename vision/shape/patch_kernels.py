"""The patch fit's inner loop, compiled (numba): one pass over the samples builds the Gauss-Newton
system of ``patch.fit`` and, on the last pass, the per-block systems of its jackknife.

Parameters, in this order: ``t`` (2), ``A`` (4, row-major), ``v`` (2) of the plane homography
``q = (A p + t) / (1 + v.p)``, then the light's gain ``a`` and offset ``b`` (``T ~ a I(q) + b``).
Units: pixels of the image crop; grey levels.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vision.image import F64
from vision.shape import small_kernels as sk
from vision.shape.small_kernels import compiled

NP = 10
"""Parameters of the fit."""


@compiled(inline="always")  # one call site (gauss_newton): compiled once, in it
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
    H = np.zeros((NP, NP), np.float64)
    g = np.zeros(NP)
    nb = nblocks if blocks else 1
    Hb = np.zeros((nb, NP, NP))
    Gb = np.zeros((nb, NP), np.float64)
    r = np.zeros(n)
    inside = np.empty(n, np.bool_)  # each set below (np.zeros of bool: one more compile)
    J = np.empty(NP)
    for i in range(n):
        px, py = pts[i, 0], pts[i, 1]
        wp = 1.0 + v0 * px + v1 * py
        qx = (a00 * px + a01 * py + t0) / wp
        qy = (a10 * px + a11 * py + t1) / wp
        inside[i] = qx >= 1.0 and qy >= 1.0 and qx <= w - 2.0 and qy <= h - 2.0
        if not inside[i]:
            continue
        I = sk.bilinear(crop, qx, qy)
        res = ga * I + gb_ - T[i]
        r[i] = res
        if sd > 0:
            u2 = (res / (tukey_c * sd)) ** 2
            if u2 >= 1.0:
                continue
            wt = (1.0 - u2) ** 2
        else:
            wt = 1.0
        ax = ga * sk.bilinear(gx, qx, qy) / wp
        ay = ga * sk.bilinear(gy, qx, qy) / wp
        aq = ax * qx + ay * qy
        J[0], J[1] = ax, ay
        J[2], J[3], J[4], J[5] = ax * px, ax * py, ay * px, ay * py
        J[6], J[7] = -aq * px, -aq * py
        J[8], J[9] = I, 1.0
        k = block[i] if blocks else 0  # per block only (one block without): the whole system is their sum
        for p in range(NP):
            wj = wt * J[p]
            Gb[k, p] += wj * res
            for q in range(p, NP):
                Hb[k, p, q] += wj * J[q]
    for k in range(nb):
        for p in range(NP):
            g[p] += Gb[k, p]
            for q in range(p, NP):
                H[p, q] += Hb[k, p, q]
    for p in range(NP):
        for q in range(p):
            H[p, q] = H[q, p]
            for k in range(nb if blocks else 0):
                Hb[k, p, q] = Hb[k, q, p]
    return H, g, Hb, Gb, r, inside


@compiled(inline="always")  # in gauss_newton
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


@compiled()
def gauss_newton(crop: NDArray[np.float32], gx: NDArray[np.float32], gy: NDArray[np.float32], pts: F64, T: F64,
                 block: NDArray[np.int64], nblocks: int, par: F64, iterations: int, tukey_c: float, r_max: float,
                 scale: float, tilt_prior: float
                 ) -> tuple[int, F64, F64, F64, F64, F64, F64, NDArray[np.bool_], float, float, float, float, int]:
    """``patch.fit``'s Gauss-Newton loop from ``par`` (changed in place; its light, gain and offset, first set
    by least squares at the start): Tukey weights from the residuals'
    robust spread after the first pass, a prior of 1-sigma ``tilt_prior`` (change of scale across the
    part, ``r_max`` px) on the perspective terms, stopped when a step moves the part by less than
    5/1000 px; the last pass also builds the per-block systems of the jackknife.

    Returns ``(status, par, H, g, Hb, Gb, r, inside, sd, ncc, sw, swr, cnt)`` (the last four: ``ncc_of``
    and ``weighted_rss`` at the end; 0 on failure): status 1 converged, 0 out of iterations,
    -1 failed (half the samples outside the crop, the fit ran more than ``r_max`` from its start, its
    scale left 0.7-1.4x ``scale``, or a tilt past 0.2 over the part)."""
    n = pts.shape[0]
    t0, t1 = par[0], par[1]
    converged = False
    failed = False
    sd = 0.0
    ncc = 0.0
    # one call site each of the inlined normal equations and light moments, one return: each copy of
    # inlined code and each return of the 13-tuple is a share of a fresh machine's first start
    for it in range(-1, iterations + 1):
        last = it >= 0 and (converged or it == iterations)
        H, g, Hb, Gb, r, inside = normal_equations(crop, gx, gy, pts, T, block, nblocks, par, sd, tukey_c, last)
        n_in = 0
        for i in range(n):
            n_in += 1 if inside[i] else 0
        if n_in < 0.5 * n:
            failed = True
            break
        if it < 0 or last:
            mi, mt, sxx, stt, sxt = light_moments(r, T, inside)
            if last:
                # the correlation of a I + b with the patch at the final pose
                den = math.sqrt(sxx * stt)
                ncc = sxt / den if den > 0 else 0.0
                break
            # the light to start from: T ~ a I + b at the start (least squares over the samples inside)
            a = sxt / sxx if sxx > 0 else 0.0
            par[8] = a if abs(a) > 1e-6 else 1e-6
            par[9] = mt - a * mi
            continue
        # a prior on the perspective terms (a view tilted by a few degrees: v r_max ~ 0.01): a round or
        # featureless part does not trade its position for a made-up tilt
        Hp = H.copy()
        s1 = sd if sd > 0 else 1.0
        prior = s1 * s1 * (r_max / tilt_prior) ** 2
        Hp[6, 6] += prior
        Hp[7, 7] += prior
        gp = g.copy()
        gp[6] += prior * par[6]
        gp[7] += prior * par[7]
        tr = 0.0
        for k in range(NP):
            tr += H[k, k]
        reg = 1e-9 * tr
        for k in range(NP):
            Hp[k, k] += reg
        d, ok = sk.solve(Hp, gp)
        if not ok:
            failed = True
            break
        for k in range(NP):  # loops, not array expressions (each compiles a ufunc kernel of its own)
            d[k] = -d[k]
            par[k] += d[k]
        # the residuals' robust spread for the next pass's Tukey weights (glints, clutter, an occluder: 0)
        ar = np.empty(n_in)
        j = 0
        for i in range(n):
            if inside[i]:
                ar[j] = abs(r[i])
                j += 1
        sd = 1.4826 * sk.median(ar) + 1e-6
        det = par[2] * par[5] - par[3] * par[4]
        if math.hypot(par[0] - t0, par[1] - t1) > r_max or not 0.5 * scale ** 2 < abs(det) < 2.0 * scale ** 2 \
                or max(abs(par[6]), abs(par[7])) * r_max > 0.2:
            failed = True
            break
        if it >= 1 and abs(d[0]) + abs(d[1]) < 5e-3 and max(abs(d[2]), abs(d[3]), abs(d[4]), abs(d[5])) * r_max < 5e-3:
            converged = True
    # the textbook covariance's sums, here (not one more compiled entry)
    sw, swr, cnt = 0.0, 0.0, 0
    if not failed:
        sw, swr, cnt = weighted_rss(r, inside, sd, tukey_c)
    status = -1 if failed else (1 if converged else 0)
    return status, par, H, g, Hb, Gb, r, inside, sd, ncc, sw, swr, cnt


@compiled(inline="always")  # in gauss_newton
def ncc_of(r: F64, T: F64, inside: NDArray[np.bool_]) -> float:
    """Normalised correlation of the fitted grey values (``r + T``: ``a I + b``) with the patch's ``T``
    over the samples ``inside``."""
    _, _, saa, sbb, sab = light_moments(r, T, inside)
    den = math.sqrt(saa * sbb)
    return sab / den if den > 0 else 0.0


@compiled(inline="always")  # in gauss_newton and ncc_of
def light_moments(r: F64, T: F64, inside: NDArray[np.bool_]) -> tuple[float, float, float, float, float]:
    """Means and centred second moments of the image's grey values (``r + T``) and the patch's ``T``
    over the samples ``inside``: ``(mean_i, mean_t, s_ii, s_tt, s_it)`` (loops, not numpy's masks and
    reductions: each of those costs a fresh machine's first start a compile). All 0 when none is inside."""
    n = r.shape[0]
    ma, mb, cnt = 0.0, 0.0, 0
    for i in range(n):
        if inside[i]:
            ma += r[i] + T[i]
            mb += T[i]
            cnt += 1
    if cnt == 0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    ma /= cnt
    mb /= cnt
    saa, sbb, sab = 0.0, 0.0, 0.0
    for i in range(n):
        if inside[i]:
            da, db = r[i] + T[i] - ma, T[i] - mb
            saa += da * da
            sbb += db * db
            sab += da * db
    return ma, mb, saa, sbb, sab
