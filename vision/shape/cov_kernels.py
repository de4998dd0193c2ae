"""``uncertainty``'s covariances, compiled (numba): the same arithmetic in one call per fit (pick speed).

``uncertainty.py`` keeps the numpy versions (the reference the tests compare these with and the text
that says why); a search calls these, one per answered match's edge fit and patch fit, where numpy's
per-call overhead over 16 small blocks cost about a millisecond a match. Units as there: pixels
(level 0) and radians.

A search reaches three compiled entries, ``edge_system``, ``block_systems`` and ``honest_systems`` (the
rest are inlined in them); ``edge_cov`` and ``honest_cov`` join them in Python: each compiled function
costs a fresh machine a share of the matcher's first start.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vision.image import F64
from vision.shape import small_kernels as sk
from vision.shape.small_kernels import compiled
from vision.shape.uncertainty import JACKKNIFE_BLOCKS, rss_at_optimum


@compiled(inline="always")  # one call site in a search: compiled there only
def blocks_of(pts: F64) -> NDArray[np.int64]:
    """``uncertainty.blocks_of``: each point's block on a ``JACKKNIFE_BLOCKS``-square grid over the points."""
    k = JACKKNIFE_BLOCKS
    lo0, lo1, hi0, hi1 = pts[0, 0], pts[0, 1], pts[0, 0], pts[0, 1]
    for i in range(1, pts.shape[0]):
        lo0, hi0 = min(lo0, pts[i, 0]), max(hi0, pts[i, 0])
        lo1, hi1 = min(lo1, pts[i, 1]), max(hi1, pts[i, 1])
    sp0, sp1 = max(hi0 - lo0, 1e-9), max(hi1 - lo1, 1e-9)
    out = np.empty(pts.shape[0], np.int64)
    for i in range(pts.shape[0]):
        c0 = min(int((pts[i, 0] - lo0) / sp0 * k), k - 1)
        c1 = min(int((pts[i, 1] - lo1) / sp1 * k), k - 1)
        out[i] = c1 * k + c0
    return out


@compiled(inline="always")  # one call site in a search: compiled there only
def jackknife_cov(H: F64, g: F64, Hb: F64, Gb: F64) -> F64:
    """``uncertainty.jackknife_of``: one Gauss-Newton step from the optimum without each block that holds
    points, ``(m-1)/m sum (p_k - mean)^2``; all infinite with fewer than 4 such blocks or a singular one."""
    k = H.shape[0]
    nb = Hb.shape[0]
    used = np.empty(nb, np.bool_)  # each set below
    m = 0
    for b in range(nb):
        t = 0.0
        for i in range(k):
            for j in range(k):
                t += abs(Hb[b, i, j])
        used[b] = t > 0
        m += 1 if t > 0 else 0
    if m < 4:
        return np.full((k, k), np.inf)
    tr = 0.0
    for i in range(k):
        tr += H[i, i]
    reg = 1e-9 * tr
    S = np.empty((m, k), np.float64)
    A = np.empty((k, k), np.float64)
    rhs = np.empty(k)
    j = 0
    for b in range(nb):
        if not used[b]:
            continue
        for p in range(k):
            rhs[p] = g[p] - Gb[b, p]
            for q in range(k):
                A[p, q] = H[p, q] - Hb[b, p, q]
            A[p, p] += reg
        x, ok = sk.solve(A, rhs)
        if not ok:
            return np.full((k, k), np.inf)
        for p in range(k):
            S[j, p] = -x[p]
        j += 1
    mean = np.zeros(k)
    for i in range(m):
        for p in range(k):
            mean[p] += S[i, p]
    for p in range(k):
        mean[p] /= m
    out = np.zeros((k, k), np.float64)
    for i in range(m):
        for p in range(k):
            dp = S[i, p] - mean[p]
            for q in range(k):
                out[p, q] += dp * (S[i, q] - mean[q])
    f = (m - 1) / m
    for p in range(k):
        for q in range(k):
            out[p, q] *= f
    return out


@compiled(inline="always")  # one call site in a search: compiled there only
def classical_cov(H: F64, s2: float, corr: float) -> F64:
    """``uncertainty.classical_of``: ``s2 H^-1 corr``; all infinite where ``H`` fixes a direction not at all."""
    k = H.shape[0]
    Hi, ok = sk.inv(H)
    if not ok:
        return np.full((k, k), np.inf)
    for i in range(k):
        if not Hi[i, i] > 0:
            return np.full((k, k), np.inf)
        for j in range(k):
            if not np.isfinite(Hi[i, j]):
                return np.full((k, k), np.inf)
    f = s2 * corr
    for i in range(k):
        for j in range(k):
            Hi[i, j] *= f
    return Hi


@compiled()
def _sandwich(M: F64, C: F64) -> F64:
    """``M C M^T`` (3, 3) of ``M`` (3, k), ``C`` (k, k)."""
    k = C.shape[0]
    out = np.zeros((3, 3), np.float64)
    for a in range(3):
        for p in range(k):
            map_ = M[a, p]
            if map_ == 0.0:
                continue
            for q in range(k):
                cq = map_ * C[p, q]
                for b in range(3):
                    out[a, b] += cq * M[b, q]
    return out


@compiled()
def _finite(C: F64) -> bool:
    """Every entry of ``C`` (k, k) finite."""
    for i in range(C.shape[0]):
        for j in range(C.shape[1]):
            if not math.isfinite(C[i, j]):
                return False
    return True


@compiled(inline="always")  # one call site in a search: compiled there only
def honest(Cc: F64, Cj: F64, M: F64) -> F64:
    """``uncertainty.honest_of``: the textbook covariance of (x, y, theta) widened by as much as the
    jackknife's exceeds it on any of x, y, theta (``M`` maps the parameters to them)."""
    if not _finite(Cc):
        return np.full((3, 3), np.inf)
    C = _sandwich(M, Cc)
    if not _finite(Cj):
        return C
    J = _sandwich(M, Cj)
    excess = 1.0
    for i in range(3):
        excess = max(excess, J[i, i] / max(C[i, i], 1e-30))
    for i in range(3):
        for j in range(3):
            C[i, j] *= excess
    return C


@compiled()
def block_systems(pts: F64, J: F64, r: F64, wgt: F64) -> tuple[F64, F64, F64, F64, float, float, int]:
    """``uncertainty.block_systems``: the weighted normal equations ``H``, ``g`` in all and per block
    (``Hb``, ``Gb``; blocks over ``pts``), and the weights' sum, the weighted residuals' square sum and
    the points weighted (for the textbook covariance)."""
    n, k = J.shape
    nb = JACKKNIFE_BLOCKS ** 2
    block = blocks_of(pts)
    Hb = np.zeros((nb, k, k))
    Gb = np.zeros((nb, k), np.float64)
    sw, swr, n_eff = 0.0, 0.0, 0
    for i in range(n):
        w = wgt[i]
        if w == 0.0:
            continue
        b = block[i]
        for p in range(k):
            wj = w * J[i, p]
            Gb[b, p] += wj * r[i]
            for q in range(k):
                Hb[b, p, q] += wj * J[i, q]
        sw += w
        swr += w * r[i] * r[i]
        n_eff += 1 if w > 0 else 0
    H = np.zeros((k, k), np.float64)
    g = np.zeros(k)
    for b in range(nb):
        for p in range(k):
            g[p] += Gb[b, p]
            for q in range(k):
                H[p, q] += Hb[b, p, q]
    return H, g, Hb, Gb, sw, swr, n_eff


@compiled()
def honest_systems(H: F64, g: F64, Hb: F64, Gb: F64, s2: float, corr: float, M: F64) -> F64:
    """``honest`` of the textbook covariance ``s2 H^-1 corr`` and the block jackknife of a fit's normal
    equations in all (``H``, ``g``) and per block (``Hb``, ``Gb``): its (x, y, theta) covariance (3, 3)."""
    return honest(classical_cov(H, s2, corr), jackknife_cov(H, g, Hb, Gb), M)


def honest_cov(pts: F64, J: F64, r: F64, wgt: F64, corr: float, M: F64) -> F64:
    """``uncertainty.honest_cov``: the textbook and block-jackknife covariances of a weighted least-squares
    fit (``J``'s columns, residuals ``r``, weights ``wgt``; blocks over ``pts``), merged (``honest``)."""
    k = J.shape[1]
    H, g, Hb, Gb, sw, swr, n_eff = block_systems(pts, np.ascontiguousarray(J, dtype=np.float64),
                                                 np.ascontiguousarray(r, dtype=np.float64),
                                                 np.ascontiguousarray(wgt, dtype=np.float64))
    if n_eff <= k + 2:
        return np.full((3, 3), np.inf)
    try:  # numpy's solve here: one compiled entry fewer to build on a fresh machine
        step = np.asarray(np.linalg.solve(H, g), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
    s2 = rss_at_optimum(swr, g, step) / max(sw * (n_eff - k) / n_eff, 1e-12)
    return np.asarray(honest_systems(H, g, Hb, Gb, s2, corr, np.ascontiguousarray(M, dtype=np.float64)))


@compiled()
def edge_system(off: F64, ok: NDArray[np.bool_], m: F64, q: F64, n: F64, th: float, sc: float,
                perspective: bool) -> tuple[F64, F64, F64, F64]:
    """``uncertainty.edge_system`` in loops (pick speed: numpy's two dozen small calls cost about 0.1 ms
    a match): the Jacobian, the residuals ``-off``, the weights and the map of the parameters to
    (x, y, theta)."""
    c, s = math.cos(th), math.sin(th)
    N = off.shape[0]
    wgt = np.zeros(N)
    r = np.empty(N)
    for i in range(N):
        r[i] = -off[i]
        if ok[i]:
            o = min(max(off[i], -1.0), 1.0)
            wgt[i] = (1 - o * o) ** 2
    k = 8 if perspective else 4
    J = np.empty((N, k), np.float64)
    M = np.zeros((3, k), np.float64)
    M[0, 0] = M[1, 1] = 1.0
    if not perspective:
        M[2, 2] = 1.0
        for i in range(N):
            mx, my, nx, ny = m[i, 0], m[i, 1], n[i, 0], n[i, 1]
            J[i, 0], J[i, 1] = nx, ny
            J[i, 2] = nx * sc * (-s * mx + c * my) + ny * sc * (-c * mx - s * my)
            J[i, 3] = nx * (c * mx + s * my) + ny * (-s * mx + c * my)
        return J, r, wgt, M
    dx = np.empty(N)
    dy = np.empty(N)
    for i in range(N):
        mx, my, nx, ny = m[i, 0], m[i, 1], n[i, 0], n[i, 1]
        nq = nx * q[i, 0] + ny * q[i, 1]
        J[i, 0], J[i, 1], J[i, 2], J[i, 3] = nx, ny, nx * mx, nx * my
        J[i, 4], J[i, 5], J[i, 6], J[i, 7] = ny * mx, ny * my, -nq * mx, -nq * my
        dx[i] = q[i, 0] - sc * (mx * c + my * s)
        dy[i] = q[i, 1] - sc * (-mx * s + my * c)
    l00, l10 = sc * c, -sc * s
    r2 = l00 * l00 + l10 * l10
    cx, cy = sk.median(dx), sk.median(dy)
    M[2, 2], M[2, 4], M[2, 6] = l10 / r2, -l00 / r2, (-l10 * cx + l00 * cy) / r2
    return J, r, wgt, M


def edge_cov(off: F64, ok: NDArray[np.bool_], m: F64, q: F64, n: F64, th: float, sc: float, corr: float,
             perspective: bool) -> F64:
    """``uncertainty.edge_cov``: the covariance (3, 3) of (x, y, theta) of an edge fit from its points'
    normal residuals ``off`` (px), over a similarity or, with ``perspective``, the plane homography."""
    m = np.ascontiguousarray(m, dtype=np.float64)
    J, r, wgt, M = edge_system(np.ascontiguousarray(off, dtype=np.float64), np.ascontiguousarray(ok, dtype=np.bool_),
                               m, np.ascontiguousarray(q, dtype=np.float64),
                               np.ascontiguousarray(n, dtype=np.float64), float(th), float(sc), bool(perspective))
    return honest_cov(m, J, r, wgt, corr, M)
