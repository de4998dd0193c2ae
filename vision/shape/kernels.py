"""Compiled measurements of image edges at the model's points and along their normals (numba).

The refinement's (``refine``) and the multi-image teach's per-point samples, each one pass over the
model points in one call (the numpy versions spent most of their time in call overhead on a few
hundred points). Places ``q`` and lengths are in pixels of the image (or crop) sampled, normals
``n`` unit vectors in it. Sampling follows ``vision.image.bilinear`` exactly (pixel centres at
integers, clamped at the border). Compiled on first use and cached on disk (``cache=True``);
``warmup.warm_up`` loads them.

- ``associate``: nearest image edge of matching orientation along each model normal.
- ``profile_centroids``: the centroid edge offset, contrast and cleanliness of each normal profile.
- ``magnitudes``: the gradient magnitude at each place; ``percentile75`` of such values.

The Gauss-Newton loops built on them are in ``fit_kernels``, the discrete search's loops in
``search_kernels``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vision.shape import small_kernels
from vision.shape.small_kernels import compiled

F64 = NDArray[np.float64]


@compiled()  # not inlined by numba: LLVM inlines it in its three callers
def _bilinear2(G: NDArray[np.float32], x: float, y: float) -> tuple[float, float]:
    h, w = G.shape[0], G.shape[1]
    x = min(max(x, 0.0), w - 1.001)
    y = min(max(y, 0.0), h - 1.001)
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    a0, a1 = G[y0, x0, 0], G[y0, x0, 1]
    b0, b1 = G[y0, x0 + 1, 0], G[y0, x0 + 1, 1]
    c0, c1 = G[y0 + 1, x0, 0], G[y0 + 1, x0, 1]
    d0, d1 = G[y0 + 1, x0 + 1, 0], G[y0 + 1, x0 + 1, 1]
    t0 = a0 + (b0 - a0) * fx
    t1 = a1 + (b1 - a1) * fx
    u0 = c0 + (d0 - c0) * fx
    u1 = c1 + (d1 - c1) * fx
    return t0 + (u0 - t0) * fy, t1 + (u1 - t1) * fy


@compiled()
def associate(G: NDArray[np.float32], q: F64, n: F64, half: int, thr: float
              ) -> tuple[F64, NDArray[np.bool_], F64, F64]:
    """Per point: signed distance to the nearest edge along the normal within ``half`` px
    (Gaussian peak fit), whether one was found, ``|cos|`` of the orientation difference there,
    and the sign of the gradient along the normal. An edge: gradient component along the normal
    >= ``thr``, within ~25 deg of the normal, a local maximum along it."""
    npts = q.shape[0]
    k = 2 * half + 1
    d = np.zeros(npts)
    found = np.empty(npts, np.bool_)  # found and sign set below (np.zeros of bool, np.ones: compiles of their own)
    cosd = np.zeros(npts)
    sign = np.empty(npts)
    gs = np.empty(k)
    g = np.empty(k)
    gm2 = np.empty(k)
    for i in range(npts):
        nx, ny = n[i, 0], n[i, 1]
        found[i] = False
        sign[i] = 1.0
        for j in range(k):
            t = j - half
            gx, gy = _bilinear2(G, q[i, 0] + t * nx, q[i, 1] + t * ny)
            s = gx * nx + gy * ny
            gs[j] = s
            m2 = gx * gx + gy * gy
            gm2[j] = m2
            a = abs(s)
            g[j] = a if (a >= thr and a * a >= 0.81 * m2) else 0.0
        best, best_cost = -1, 1 << 30
        for j in range(1, k - 1):
            if g[j] > 0.0 and g[j] >= g[j - 1] and g[j] > g[j + 1]:
                cost = abs(j - half)
                if cost < best_cost:
                    best, best_cost = j, cost
        if best < 0:
            continue
        lm = math.log(max(g[best - 1], 1e-6))
        l0 = math.log(max(g[best], 1e-6))
        lp = math.log(max(g[best + 1], 1e-6))
        den = lm - 2 * l0 + lp
        off = 0.5 * (lm - lp) / den if den < -1e-9 else 0.0
        off = min(max(off, -0.5), 0.5)
        found[i] = True
        d[i] = (best - half) + off
        cosd[i] = abs(gs[best]) / math.sqrt(max(gm2[best], 1e-12))
        sign[i] = 1.0 if gs[best] >= 0 else -1.0
    return d, found, cosd, sign


@compiled()
def profile_centroids(img: NDArray[np.float32], q: F64, n: F64, half: int) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Per point: the centroid offset of the profile's differences along the normal, the signed
    contrast, and whether the profile is one clean monotonic step (``image.profile_ok``)."""
    npts = q.shape[0]
    off = np.zeros(npts)
    S = np.zeros(npts)
    clean = np.empty(npts, np.bool_)  # each set below
    k = 2 * half + 1
    prof = np.empty(k)
    for i in range(npts):
        for j in range(k):
            t = j - half
            prof[j] = small_kernels.bilinear(img, q[i, 0] + t * n[i, 0], q[i, 1] + t * n[i, 1])
        s, m = 0.0, 0.0
        for j in range(k - 1):
            dj = prof[j + 1] - prof[j]
            s += dj
            m += (j - half + 0.5) * dj
        S[i] = s
        off[i] = m / s if abs(s) > 1e-9 else 0.0
        sg = 1.0 if s > 0 else (-1.0 if s < 0 else 0.0)
        wrong = 0.0
        for j in range(k - 1):
            dj = -(prof[j + 1] - prof[j]) * sg
            if dj > 0:
                wrong += dj
        clean[i] = wrong <= 0.1 * abs(s)
    return off, S, clean


@compiled()
def magnitudes(G: NDArray[np.float32], q: F64) -> F64:
    """Gradient magnitude at each place ``q`` (N, 2) of the two-channel gradient image ``G``:
    ``hypot`` of ``vision.image.bilinear`` of each channel, in one pass."""
    out = np.empty(q.shape[0])
    for i in range(q.shape[0]):
        g0, g1 = _bilinear2(G, q[i, 0], q[i, 1])
        out[i] = math.hypot(g0, g1)
    return out


def percentile75(a: F64) -> float:
    """``np.percentile(a, 75)`` (its default linear method, the same bits) without its per-call
    overhead, which dominated on the few hundred points of a model: the two values it needs by
    ``np.partition``."""
    n = a.shape[0]
    v = 0.75 * n + 0.25 - 1.0
    lo = min(max(int(math.floor(v)), 0), n - 1)
    hi = min(lo + 1, n - 1)
    t = v - lo
    part = np.partition(a, (lo, hi))
    s_lo, s_hi = float(part[lo]), float(part[hi])
    d = s_hi - s_lo
    return s_hi - d * (1.0 - t) if t >= 0.5 else s_lo + d * t
