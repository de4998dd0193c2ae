"""``uncertainty``'s covariances, compiled (numba): the same arithmetic in one call per fit (pick speed).

``uncertainty.py`` keeps the numpy versions (the reference the tests compare these with and the text
that says why); a search calls these, one per answered match's edge fit and patch fit, where numpy's
per-call overhead over 16 small blocks cost about a millisecond a match. Units as there: pixels
(level 0) and radians.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from vision.image import F64
from vision.shape.uncertainty import JACKKNIFE_BLOCKS


@njit(cache=True)
def blocks_of(pts: F64) -> NDArray[np.int64]:
    """``uncertainty.blocks_of``: each point's block on a ``JACKKNIFE_BLOCKS``-square grid over the points."""
    k = JACKKNIFE_BLOCKS
    lo0, lo1 = pts[:, 0].min(), pts[:, 1].min()
    sp0, sp1 = max(pts[:, 0].max() - lo0, 1e-9), max(pts[:, 1].max() - lo1, 1e-9)
    out = np.empty(pts.shape[0], np.int64)
    for i in range(pts.shape[0]):
        c0 = min(int((pts[i, 0] - lo0) / sp0 * k), k - 1)
        c1 = min(int((pts[i, 1] - lo1) / sp1 * k), k - 1)
        out[i] = c1 * k + c0
    return out


@njit(cache=True)
def jackknife_cov(H: F64, g: F64, Hb: F64, Gb: F64) -> F64:
    """``uncertainty.jackknife_of``: one Gauss-Newton step from the optimum without each block that holds
    points, ``(m-1)/m sum (p_k - mean)^2``; all infinite with fewer than 4 such blocks or a singular one."""
    k = H.shape[0]
    bad = np.full((k, k), np.inf)
    used = np.zeros(Hb.shape[0], np.bool_)
    for b in range(Hb.shape[0]):
        used[b] = np.abs(Hb[b]).sum() > 0
    m = int(used.sum())
    if m < 4:
        return bad
    reg = 1e-9 * np.trace(H)
    S = np.empty((m, k))
    j = 0
    try:
        for b in range(Hb.shape[0]):
            if not used[b]:
                continue
            A = H - Hb[b]
            for i in range(k):
                A[i, i] += reg
            S[j] = -np.linalg.solve(A, g - Gb[b])
            j += 1
    except Exception:  # noqa: BLE001 - numba raises LinAlgError as a plain exception
        return bad
    mean = np.zeros(k)
    for i in range(m):
        mean += S[i]
    mean /= m
    D = S - mean
    return (m - 1) / m * (np.ascontiguousarray(D.T) @ D)


@njit(cache=True)
def classical_cov(H: F64, s2: float, corr: float) -> F64:
    """``uncertainty.classical_of``: ``s2 H^-1 corr``; all infinite where ``H`` fixes a direction not at all."""
    k = H.shape[0]
    try:
        Hi = np.linalg.inv(H)
    except Exception:  # noqa: BLE001
        return np.full((k, k), np.inf)
    if not np.all(np.isfinite(Hi)):
        return np.full((k, k), np.inf)
    for i in range(k):
        if not Hi[i, i] > 0:
            return np.full((k, k), np.inf)
    return np.asarray(Hi * (s2 * corr), dtype=np.float64)


@njit(cache=True)
def honest(Cc: F64, Cj: F64, M: F64) -> F64:
    """``uncertainty.honest_of``: the textbook covariance of (x, y, theta) widened by as much as the
    jackknife's exceeds it on any of x, y, theta (``M`` maps the parameters to them)."""
    if not np.all(np.isfinite(Cc)):
        return np.full((3, 3), np.inf)
    Mt = np.ascontiguousarray(M.T)
    C = M @ np.ascontiguousarray(Cc) @ Mt
    if not np.all(np.isfinite(Cj)):
        return C
    J = M @ np.ascontiguousarray(Cj) @ Mt
    excess = 0.0
    for i in range(3):
        excess = max(excess, J[i, i] / max(C[i, i], 1e-30))
    return C * max(excess, 1.0)


@njit(cache=True)
def honest_cov(pts: F64, J: F64, r: F64, wgt: F64, corr: float, M: F64) -> F64:
    """``uncertainty.honest_cov``: the textbook and block-jackknife covariances of a weighted least-squares
    fit (``J``'s columns, residuals ``r``, weights ``wgt``; blocks over ``pts``), merged (``honest``)."""
    n, k = J.shape
    nb = JACKKNIFE_BLOCKS ** 2
    block = blocks_of(pts)
    Hb = np.zeros((nb, k, k))
    Gb = np.zeros((nb, k))
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
    H = Hb.sum(axis=0)
    g = Gb.sum(axis=0)
    if n_eff <= k + 2:
        Cc = np.full((k, k), np.inf)
    else:
        Cc = classical_cov(H, swr / max(sw * (n_eff - k) / n_eff, 1e-12), corr)
    return honest(Cc, jackknife_cov(H, g, Hb, Gb), M)


@njit(cache=True)
def edge_cov(off: F64, ok: NDArray[np.bool_], m: F64, q: F64, n: F64, th: float, sc: float, corr: float,
             perspective: bool) -> F64:
    """``uncertainty.edge_cov``: the covariance (3, 3) of (x, y, theta) of an edge fit from its points'
    normal residuals ``off`` (px), over a similarity or, with ``perspective``, the plane homography."""
    c, s = math.cos(th), math.sin(th)
    N = off.shape[0]
    wgt = np.zeros(N)
    for i in range(N):
        if ok[i]:
            o = min(max(off[i], -1.0), 1.0)
            wgt[i] = (1 - o * o) ** 2
    if not perspective:
        J = np.empty((N, 4))
        for i in range(N):
            mx, my, nx, ny = m[i, 0], m[i, 1], n[i, 0], n[i, 1]
            J[i, 0], J[i, 1] = nx, ny
            J[i, 2] = nx * sc * (-s * mx + c * my) + ny * sc * (-c * mx - s * my)
            J[i, 3] = nx * (c * mx + s * my) + ny * (-s * mx + c * my)
        return honest_cov(m, J, -off, wgt, corr, np.eye(3, 4))
    J = np.empty((N, 8))
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
    cx, cy = np.median(dx), np.median(dy)
    M = np.zeros((3, 8))
    M[0, 0] = M[1, 1] = 1.0
    M[2, 2], M[2, 4], M[2, 6] = l10 / r2, -l00 / r2, (-l10 * cx + l00 * cy) / r2
    return honest_cov(m, J, -off, wgt, corr, M)
