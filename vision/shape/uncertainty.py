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
from numpy.typing import NDArray

from vision.image import F64

JACKKNIFE_BLOCKS = 4
"""The grid of jackknife blocks over the part is this many blocks on a side (up to 16 blocks)."""


def blocks_of(pts: F64) -> NDArray[np.int64]:
    """Each point's jackknife block: a ``JACKKNIFE_BLOCKS``-square grid over the points' extent."""
    k = JACKKNIFE_BLOCKS
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    cell = np.minimum(((pts - lo) / np.maximum(hi - lo, 1e-9) * k).astype(np.int64), k - 1)
    return np.asarray(cell[:, 1] * k + cell[:, 0], dtype=np.int64)


def block_systems(pts: F64, J: F64, r: F64, wgt: F64) -> tuple[F64, F64, F64, F64]:
    """The weighted normal equations ``H = J^T W J``, ``g = J^T W r`` in all and per block."""
    nb = JACKKNIFE_BLOCKS ** 2
    b = blocks_of(pts)
    Jw = J * wgt[:, None]
    k = J.shape[1]
    Hb = np.zeros((nb, k, k))
    Gb = np.zeros((nb, k))
    for i in np.unique(b).tolist():
        sel = b == i
        Hb[i] = Jw[sel].T @ J[sel]
        Gb[i] = Jw[sel].T @ r[sel]
    return Hb.sum(axis=0), Gb.sum(axis=0), Hb, Gb


def jackknife_of(H: F64, g: F64, Hb: F64, Gb: F64) -> F64:
    """Covariance (k, k) of the parameters by the block jackknife: one Gauss-Newton step from the
    optimum without each block (``(m-1)/m sum (p_k - mean)^2`` over the m blocks that hold points)."""
    used = np.abs(Hb).reshape(len(Hb), -1).sum(axis=1) > 0
    if used.sum() < 4:
        return np.full(H.shape, np.inf)
    reg = 1e-9 * np.trace(H) * np.eye(len(H))
    try:
        S = -np.linalg.solve(H[None] - Hb[used] + reg[None], (g[None] - Gb[used])[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return np.full(H.shape, np.inf)
    D = S - S.mean(axis=0)
    m = len(S)
    return np.asarray((m - 1) / m * (D.T @ D), dtype=np.float64)


def classical_of(H: F64, s2: float, corr: float) -> F64:
    """The textbook covariance ``s^2 H^-1`` times ``corr`` (how many samples share one independent
    error: neighbouring pixels see the same blur). Where the data barely fix a parameter (the turn of
    a round outline) it is large; a jackknife of few blocks can miss that."""
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full(H.shape, np.inf)
    if not (np.all(np.isfinite(Hi)) and np.all(np.diag(Hi) > 0)):
        return np.full(H.shape, np.inf)  # a direction the data do not fix at all
    return np.asarray(Hi * s2 * corr, dtype=np.float64)


def honest_of(Cc: F64, Cj: F64, M: F64) -> F64:
    """The pose's covariance (3, 3) of (x, y, theta): the textbook one widened by as much as the
    jackknife exceeds it on any of x, y, theta; ``M`` (3, k) maps the parameters to (x, y, theta)."""
    ok_c, ok_j = bool(np.all(np.isfinite(Cc))), bool(np.all(np.isfinite(Cj)))
    if not ok_c:
        # a direction the data do not fix (a round outline's turn): no block can show it either
        return np.full((3, 3), np.inf)
    Cc = M @ Cc @ M.T
    if not ok_j:
        return np.asarray(Cc, dtype=np.float64)
    Cj = M @ Cj @ M.T
    excess = float(np.max(np.diag(Cj) / np.maximum(np.diag(Cc), 1e-30)))
    return np.asarray(Cc * max(excess, 1.0), dtype=np.float64)


def jackknife(pts: F64, J: F64, r: F64, wgt: F64) -> F64:
    """Covariance (k, k) of a fit's parameters (``J``'s columns, residuals ``r``, weights ``wgt``) by
    the block jackknife over a grid of the points ``pts``."""
    return jackknife_of(*block_systems(pts, J, r, wgt))


def classical(J: F64, r: F64, wgt: F64, corr: float) -> F64:
    """The textbook covariance (k, k) of a fit's parameters (``classical_of``), ``s^2`` the weighted
    residual variance at the fit's optimum: ``r`` less the Gauss-Newton step ``J d`` to it
    (``rss_at_optimum``; ``r`` may be those of a simpler model's pose, as an edge fit's homography is
    judged at the similarity's points)."""
    n_eff = float(np.sum(wgt > 0))
    if n_eff <= J.shape[1] + 2:
        return np.full((J.shape[1], J.shape[1]), np.inf)
    H = J.T @ (J * wgt[:, None])
    g = (J * wgt[:, None]).T @ r
    try:
        rss = rss_at_optimum(float(np.sum(wgt * r * r)), g, np.asarray(np.linalg.solve(H, g), dtype=np.float64))
    except np.linalg.LinAlgError:
        return np.full((J.shape[1], J.shape[1]), np.inf)
    s2 = rss / max(float(np.sum(wgt)) * (n_eff - J.shape[1]) / n_eff, 1e-12)
    return classical_of(H, s2, corr)


def rss_at_optimum(swr: float, g: F64, step: F64) -> float:
    """The weighted residual square sum at the least-squares optimum of a linear system from its value
    ``swr`` at the residuals ``r``, its gradient ``g = J^T W r`` and ``step = H^-1 g``:
    ``swr - g^T H^-1 g`` (the misfit a pose short of the optimum adds is not the fit's noise: the
    textbook covariance of a homography judged at a similarity's points counted a tilted view's
    perspective as noise, three times its angle's actual error)."""
    return max(swr - float(g @ step), 0.0)


def honest_cov(pts: F64, J: F64, r: F64, wgt: F64, corr: float, M: F64 | None = None) -> F64:
    """``honest_of`` the textbook and the jackknife covariances of a fit (default ``M``: the first three
    parameters are x, y, theta)."""
    return honest_of(classical(J, r, wgt, corr), jackknife(pts, J, r, wgt),
                     np.eye(3, J.shape[1]) if M is None else M)


def _inverse_weighted(pe: F64, Ce: F64, pp: F64, Cp: F64) -> tuple[F64, F64, F64, F64, float] | None:
    """Two estimates of (x, y, theta) weighted by their inverse covariances: the weights ``We``, ``Wp``,
    the merged covariance ``C``, the merged estimate and the two's chi-square per degree of freedom;
    None when a covariance is singular."""
    d = pp - pe
    try:
        chi = float(d @ np.linalg.solve(Ce + Cp, d)) / 3.0
        We, Wp = np.linalg.inv(np.stack((Ce, Cp)))  # one batched call: the same LAPACK solve of each
        C = np.linalg.inv(We + Wp)
    except np.linalg.LinAlgError:
        return None
    return np.asarray(We, np.float64), np.asarray(Wp, np.float64), C, C @ (We @ pe + Wp @ pp), chi


def combine(pe: F64, Ce: F64, pp: F64, Cp: F64) -> tuple[F64, F64, float]:
    """Merge two estimates of (x, y, theta) by their covariances: the merged estimate, its covariance
    widened by the two's disagreement (the chi-square of their difference over its 3 degrees of
    freedom, when above 1), and that chi-square per degree of freedom (the fixed-effect reference that
    ``merge`` improves on)."""
    w = _inverse_weighted(pe, Ce, pp, Cp)
    if w is None:
        return pe, Ce, float("inf")
    _, _, C, p, chi = w
    return p, C * max(chi, 1.0), chi


def merge(pe: F64, Ce: F64, pp: F64, Cp: F64, T0: F64 | None = None) -> tuple[F64, F64, float]:
    """Merge two fits' estimates of (x, y, theta) by their covariances, with the covariance a
    random-effects model gives it: where the two differ by more than their covariances allow, the
    excess is an error that each fit has beyond its own covariance (the part's look changed, an edge
    was dragged: neither fit sees it in its own residuals). It is estimated from their difference ``d``
    by the method of moments (DerSimonian and Laird's), ``E|d_xy|^2 = tr(Ce + Cp)_xy + 4 tau_xy^2``
    (isotropic in position) and ``E d_theta^2 = (Ce + Cp)_theta + 2 tau_theta^2``, and the merged
    estimate (weighted by the fits' own covariances, as ``combine``: the sharper fit leads) gets the
    covariance it has when each fit carries ``T = diag(tau_xy^2, tau_xy^2, tau_theta^2)`` more,
    ``C + C (We T We + Wp T Wp) C``. Two fits that agree within their 1-sigma get nothing added (the
    renders); two that disagree report about the disagreement. ``T0`` (3, 3): an extra error each fit is
    known to carry already (a several-views model's spread across its teach views,
    ``ShapeModel.view_tau``), added to ``T`` and counted in the moment estimate's expectation. Returns
    the merged estimate, its covariance and the two's chi-square per degree of freedom."""
    d = pp - pe
    S = Ce + Cp if T0 is None else Ce + Cp + 2.0 * T0
    w = _inverse_weighted(pe, Ce, pp, Cp)
    if w is None:
        return pe, Ce, float("inf")
    We, Wp, C, p, chi = w
    tau_xy = max(float(d[0] ** 2 + d[1] ** 2) - float(S[0, 0] + S[1, 1]), 0.0) / 4.0
    tau_th = max(float(d[2] ** 2) - float(S[2, 2]), 0.0) / 2.0
    T = np.diag([tau_xy, tau_xy, tau_th])
    if T0 is not None:
        T = T + T0
    C_re = C + C @ (We @ T @ We + Wp @ T @ Wp) @ C
    return p, np.asarray(C_re, dtype=np.float64), chi


def view_tau(d: F64, S: F64) -> tuple[float, float]:
    """The extra error (px, rad: 1-sigma of the position on each axis and of the angle) that a fit has
    beyond its own covariance, by ``merge``'s moment estimate pooled over several pairs of fits of one
    part: ``d`` (n, 3) their differences in (x, y, theta), ``S`` (n, 3, 3) the sums of their covariances."""
    if len(d) == 0:
        return 0.0, 0.0
    xy = float(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2)) - float(np.mean(S[:, 0, 0] + S[:, 1, 1]))
    th = float(np.mean(d[:, 2] ** 2)) - float(np.mean(S[:, 2, 2]))
    return math.sqrt(max(xy, 0.0) / 4.0), math.sqrt(max(th, 0.0) / 2.0)


def sigma_of(C: F64) -> tuple[float, float]:
    """1-sigma of the angle (deg) and of the position (px, the larger axis) of a (3, 3) covariance of
    (x, y, theta)."""
    ev = np.linalg.eigvalsh(C[:2, :2])
    return math.degrees(math.sqrt(max(float(C[2, 2]), 0.0))), math.sqrt(max(float(ev[-1]), 0.0))


def edge_cov(off: F64, ok: NDArray[np.bool_], m: F64, q: F64, n: F64, th: float, sc: float, corr: float,
             perspective: bool) -> F64:
    """Covariance (3, 3) of (x, y, theta) of an edge fit (``honest_cov``): ``off`` the points' normal
    residuals (px) at the final pose, ``ok`` those used, ``m`` the model points (relative to the
    reference point), ``q`` and ``n`` the points and unit normals at the pose; over the parameters the
    fit had: a similarity (x, y, theta, scale) or, with ``perspective``, the plane homography
    ``q = (A m + c) / (1 + p.m)`` at ``p = 0`` (the angle that of ``A - c p^T``)."""
    J, wgt, M = edge_system(off, ok, m, q, n, th, sc, perspective)
    return honest_cov(m, J, -off, wgt, corr, M)


def edge_system(off: F64, ok: NDArray[np.bool_], m: F64, q: F64, n: F64, th: float, sc: float,
                perspective: bool) -> tuple[F64, F64, F64]:
    """``edge_cov``'s least-squares system: the Jacobian (N, 4) or (N, 8) of the points' normal
    offsets in the fit's parameters, the points' weights, and the map (3, k) of the parameters to
    (x, y, theta)."""
    c, s = math.cos(th), math.sin(th)
    wgt = np.where(ok, (1 - np.clip(off, -1, 1) ** 2) ** 2, 0.0)
    if not perspective:
        dqx = sc * (-s * m[:, 0] + c * m[:, 1])
        dqy = sc * (-c * m[:, 0] - s * m[:, 1])
        rx, ry = c * m[:, 0] + s * m[:, 1], -s * m[:, 0] + c * m[:, 1]
        J = np.stack([n[:, 0], n[:, 1], n[:, 0] * dqx + n[:, 1] * dqy, n[:, 0] * rx + n[:, 1] * ry], axis=1)
        return J, wgt, np.eye(3, 4)
    nx, ny, mx, my = n[:, 0], n[:, 1], m[:, 0], m[:, 1]
    nq = nx * q[:, 0] + ny * q[:, 1]
    J = np.stack([nx, ny, nx * mx, nx * my, ny * mx, ny * my, -nq * mx, -nq * my], axis=1)
    l00, l10 = sc * c, -sc * s
    r2 = l00 * l00 + l10 * l10
    # the reference point in the crop: q of a model point less its linear image
    cx = float(np.median(q[:, 0] - sc * (mx * c + my * s)))
    cy = float(np.median(q[:, 1] - sc * (-mx * s + my * c)))
    M = np.zeros((3, 8))
    M[0, 0] = M[1, 1] = 1.0
    M[2, 2], M[2, 4], M[2, 6] = l10 / r2, -l00 / r2, (-l10 * cx + l00 * cy) / r2
    return J, wgt, M
