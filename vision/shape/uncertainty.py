"""A fit's honest 1-sigma: a block jackknife of its last Gauss-Newton system, and two fits merged.

A least-squares fit's textbook covariance ``s^2 (J^T J)^-1`` takes every residual as independent. On
real images they are not: blur ties neighbouring pixels, and a shading gradient, a bevel or texture
that the model lacks moves a whole stretch of edge or a whole region of the patch one way. The
**block jackknife** sees that: the points are split into blocks (a ``JACKKNIFE_BLOCKS``-square grid
over the part), the fit is solved again without each block (one Gauss-Newton step from the optimum,
exact to first order), and the spread of those answers, ``(m-1)/m sum (p_k - mean)^2``, is the
variance. Where the residuals are independent it agrees with the textbook value; where a block pulls
the fit, it grows by as much as that block moves it.

``honest_cov`` is the textbook covariance widened by the jackknife's excess over it (where the data
barely fix a parameter the textbook value is the larger; where blocks pull, the jackknife's).
``combine`` merges two estimates of (x, y, theta) by their covariances and widens the result by their
disagreement. Units: pixels (level 0) and radians.
"""

from __future__ import annotations

import math

import numpy as np

from vision.image import F64

JACKKNIFE_BLOCKS = 4
"""The grid of jackknife blocks over the part is this many blocks on a side (up to 16 blocks)."""


def jackknife(pts: F64, J: F64, r: F64, wgt: F64) -> F64:
    """Covariance (3, 3) of (x, y, theta) by a block jackknife of the last Gauss-Newton system: one
    step from the optimum without each block of a ``JACKKNIFE_BLOCKS``-square grid over the points."""
    k = JACKKNIFE_BLOCKS
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    cell = np.minimum(((pts - lo) / np.maximum(hi - lo, 1e-9) * k).astype(np.int64), k - 1)
    block = cell[:, 1] * k + cell[:, 0]
    H = J.T @ (J * wgt[:, None])
    g = J.T @ (wgt * r)
    sol: list[F64] = []
    for b in range(k * k):
        sel = block == b
        if not (wgt[sel] > 0).any():
            continue
        Jb = J[sel]
        Hb = H - Jb.T @ (Jb * wgt[sel, None])
        gb = g - Jb.T @ (wgt[sel] * r[sel])
        try:
            sol.append(-np.linalg.solve(Hb + 1e-9 * np.eye(len(H)) * np.trace(H), gb)[:3])
        except np.linalg.LinAlgError:
            continue
    if len(sol) < 4:
        return np.full((3, 3), np.inf)
    S = np.asarray(sol)
    D = S - S.mean(axis=0)
    m = len(sol)
    return np.asarray((m - 1) / m * (D.T @ D), dtype=np.float64)


def classical(J: F64, r: F64, wgt: F64, corr: float) -> F64:
    """The textbook covariance (3, 3) of (x, y, theta): ``s^2 (J^T W J)^-1`` with ``s^2`` the weighted
    residual variance, times ``corr`` (how many samples share one independent error: neighbouring
    pixels see the same blur). Where the data barely fix a parameter (the turn of a round outline) it
    is large; a jackknife of few blocks can miss that."""
    H = J.T @ (J * wgt[:, None])
    n_eff = float(np.sum(wgt > 0))
    if n_eff <= J.shape[1] + 2:
        return np.full((3, 3), np.inf)
    s2 = float(np.sum(wgt * r * r)) / max(float(np.sum(wgt)) * (n_eff - J.shape[1]) / n_eff, 1e-12)
    try:
        C = np.linalg.pinv(H, rcond=1e-12)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
    return np.asarray(C[:3, :3] * s2 * corr, dtype=np.float64)


def honest_cov(pts: F64, J: F64, r: F64, wgt: F64, corr: float) -> F64:
    """The pose's covariance (3, 3) of (x, y, theta): the textbook one (``classical``) widened by as
    much as the block jackknife exceeds it on any of x, y, theta (errors shared by neighbouring
    points: a shading gradient, texture, a bevel the model lacks)."""
    Cc = classical(J, r, wgt, corr)
    Cj = jackknife(pts, J, r, wgt)
    if not (np.all(np.isfinite(Cc)) and np.all(np.isfinite(Cj))):
        return Cc if np.all(np.isfinite(Cc)) else Cj
    d = np.diag(Cc)
    excess = float(np.max(np.diag(Cj) / np.maximum(d, 1e-30)))
    return np.asarray(Cc * max(excess, 1.0), dtype=np.float64)


def combine(pe: F64, Ce: F64, pp: F64, Cp: F64) -> tuple[F64, F64, float]:
    """Merge two estimates of (x, y, theta) by their covariances: the merged estimate, its covariance
    widened by the two's disagreement (the chi-square of their difference over its 3 degrees of
    freedom, when above 1), and that chi-square per degree of freedom."""
    d = pp - pe
    try:
        chi = float(d @ np.linalg.solve(Ce + Cp, d)) / 3.0
        We, Wp = np.linalg.inv(Ce), np.linalg.inv(Cp)
        C = np.linalg.inv(We + Wp)
    except np.linalg.LinAlgError:
        return pe, Ce, float("inf")
    p = C @ (We @ pe + Wp @ pp)
    return p, C * max(chi, 1.0), chi


def sigma_of(C: F64) -> tuple[float, float]:
    """1-sigma of the angle (deg) and of the position (px, the larger axis) of a (3, 3) covariance of
    (x, y, theta)."""
    ev = np.linalg.eigvalsh(C[:2, :2])
    return math.degrees(math.sqrt(max(float(C[2, 2]), 0.0))), math.sqrt(max(float(ev[-1]), 0.0))


def edge_cov(off: F64, ok: np.ndarray, m: F64, q: F64, n: F64, th: float, sc: float, corr: float) -> F64:
    """Covariance (3, 3) of (x, y, theta) of an edge fit by the block jackknife: ``off`` the points'
    normal residuals (px) at the final pose, ``ok`` those used, ``m`` the model points (relative to the
    reference point), ``q`` and ``n`` the points and unit normals at the pose; a similarity
    (x, y, theta, scale)."""
    c, s = math.cos(th), math.sin(th)
    dqx = sc * (-s * m[:, 0] + c * m[:, 1])
    dqy = sc * (-c * m[:, 0] - s * m[:, 1])
    rx, ry = c * m[:, 0] + s * m[:, 1], -s * m[:, 0] + c * m[:, 1]
    J = np.stack([n[:, 0], n[:, 1], n[:, 0] * dqx + n[:, 1] * dqy, n[:, 0] * rx + n[:, 1] * ry], axis=1)
    wgt = np.where(ok, (1 - np.clip(off, -1, 1) ** 2) ** 2, 0.0)
    return honest_cov(m, J, -off, wgt, corr)
