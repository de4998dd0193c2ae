"""RPnP: the non-iterative O(n) pose of Li, Xu and Xie (2012), written from the paper; our own code
because OpenCV has no RPnP.

Input: target points ``X`` (N, 3, metres, target frame) and their *ideal normalized* image
coordinates ``xy`` (N, 2: lens distortion already removed, ``x = X_c / Z_c``). Output: candidate
poses ``(R, t)`` with ``x_cam = R @ X + t`` (``T_cam_target``), best first.

The method, as the paper describes it:

1. The *rotation axis* is the line through the two points whose images lie farthest apart
   (``P_a``, ``P_b``): their depth ratio ``u = t_b / t_a`` along the rays fixes the axis
   direction in the camera frame.
2. Every other point ``P_j`` forms a 3-point subset ``{P_a, P_b, P_j}``. The law of cosines of
   that P3P, with ``t_j = w · t_a`` eliminated, gives one fourth-order polynomial ``f_j(u)`` in
   the shared unknown ``u`` (derivation in :func:`_quartic`).
3. ``u`` minimises ``F(u) = Σ f_j(u)²``; its stationary points are the real roots of the
   seventh-order ``F'(u)``.
4. For each root the axis is known in both frames; the remaining rotation about the axis
   (``cos α``, ``sin α``) and the translation are linear in the projection equations of all N
   points (least squares), then ``(cos α, sin α)`` is normalised and ``t`` solved again.
5. The candidate with the smallest reprojection error (normalized coordinates) wins.

Refinement on pixels through the full lens model is :func:`calibration.pose.methods.refine_pose`.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError

F64 = NDArray[np.float64]

MIN_POINTS: Final = 4
_EXACT_PAIR_LIMIT: Final = 300


class RPnPError(CalibrationError):
    """The points cannot give an RPnP pose (too few, collinear, mismatched); the message says why."""


def _check(X: F64, xy: F64) -> None:
    if X.ndim != 2 or X.shape[1] != 3 or xy.ndim != 2 or xy.shape[1] != 2:
        raise RPnPError(f"RPnP needs (N, 3) target points and (N, 2) image points, got {X.shape} and {xy.shape}")
    if len(X) != len(xy):
        raise RPnPError(f"{len(X)} target points but {len(xy)} image points; give one image point per target point")
    if len(X) < MIN_POINTS:
        raise RPnPError(f"RPnP needs at least {MIN_POINTS} points, got {len(X)}: 3 points give up to four poses "
                        "(P3P) and cannot tell them apart; observe at least one more target point")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(xy))):
        raise RPnPError("the points contain NaN or infinity")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-12):
        raise RPnPError("the target points are collinear: a pose needs points spanning a plane or a volume "
                        "(the rotation about their line is undetermined)")


def _axis_pair(xy: F64) -> tuple[int, int]:
    """The two points whose images lie farthest apart (exact up to 300 points, two passes beyond)."""
    n = len(xy)
    if n <= _EXACT_PAIR_LIMIT:
        d = np.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=2)
        flat = int(np.argmax(d))
        return flat // n, flat % n
    first = int(np.argmax(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1)))
    return first, int(np.argmax(np.sum((xy - xy[first]) ** 2, axis=1)))


def _quartics(c_ab: float, c_aj: F64, c_bj: F64, k1: F64, k2: F64) -> F64:
    """Coefficients (lowest power first, one row per subset) of the P3P quartic in ``u = t_b / t_a``.

    With unit rays and ``t_b = u t_a``, ``t_j = w t_a`` the law of cosines reads
    ``t_a² q(u) = d_ab²``, ``1 + w² - 2 w c_aj = k1 q(u)`` and ``u² + w² - 2 u w c_bj = k2 q(u)``
    where ``q(u) = 1 + u² - 2 u c_ab``, ``k1 = d_aj² / d_ab²``, ``k2 = d_bj² / d_ab²``. The difference
    of the last two is linear in ``w``: ``w = N(u) / M(u)`` with ``N = (k1 - k2) q - 1 + u²`` and
    ``M = 2 (u c_bj - c_aj)``. Substituting into the second gives
    ``f(u) = N² - 2 c_aj N M + M² (1 - k1 q) = 0``, of degree four.
    """
    d = k1 - k2
    n0, n1, n2 = d - 1.0, -2.0 * c_ab * d, d + 1.0
    m0, m1 = -2.0 * c_aj, 2.0 * c_bj
    p0, p1, p2 = 1.0 - k1, 2.0 * c_ab * k1, -k1
    nn = [n0 * n0, 2 * n0 * n1, n1 * n1 + 2 * n0 * n2, 2 * n1 * n2, n2 * n2]
    nm = [n0 * m0, n0 * m1 + n1 * m0, n1 * m1 + n2 * m0, n2 * m1, np.zeros_like(m0)]
    mm = [m0 * m0, 2 * m0 * m1, m1 * m1]
    mp = [mm[0] * p0, mm[0] * p1 + mm[1] * p0, mm[0] * p2 + mm[1] * p1 + mm[2] * p0, mm[1] * p2 + mm[2] * p1,
          mm[2] * p2]
    return np.column_stack([nn[k] - 2.0 * c_aj * nm[k] + mp[k] for k in range(5)])


def _basis(z: F64) -> F64:
    """A right-handed orthonormal basis (columns) whose third column is the unit vector ``z``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _pose_about_axis(X: F64, xy: F64, z_obj: F64, z_cam: F64) -> tuple[F64, F64]:
    """Rotation ``R = B_c Rz(α) B_oᵀ`` (axis ``z_obj`` → ``z_cam``) and ``t`` from all points, linear."""
    Bo, Bc = _basis(z_obj), _basis(z_cam)
    Pp = X @ Bo  # points in the axis frame
    # R X = cos α · A + sin α · Bv + C, each (N, 3)
    A = np.outer(Pp[:, 0], Bc[:, 0]) + np.outer(Pp[:, 1], Bc[:, 1])
    Bv = np.outer(Pp[:, 0], Bc[:, 1]) - np.outer(Pp[:, 1], Bc[:, 0])
    C = np.outer(Pp[:, 2], Bc[:, 2])
    x, y = xy[:, 0], xy[:, 1]
    n = len(X)
    # row "x": (RX)_0 + t0 - x ((RX)_2 + t2) = 0; row "y" likewise with index 1
    M = np.zeros((2 * n, 5))
    b = np.zeros(2 * n)
    for r, (k, img) in enumerate(((0, x), (1, y))):
        sl = slice(r * n, (r + 1) * n)
        M[sl, 0] = A[:, k] - img * A[:, 2]
        M[sl, 1] = Bv[:, k] - img * Bv[:, 2]
        M[sl, 2 + k] = 1.0
        M[sl, 4] = -img
        b[sl] = -(C[:, k] - img * C[:, 2])
    sol = np.linalg.lstsq(M, b, rcond=None)[0]
    alpha = float(np.arctan2(sol[1], sol[0]))
    ca, sa = np.cos(alpha), np.sin(alpha)
    Rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    R = Bc @ Rz @ Bo.T
    # translation again with the rotation fixed (the normalisation of (cos, sin) moved it)
    RX = X @ R.T
    Mt = np.zeros((2 * n, 3))
    bt = np.zeros(2 * n)
    for r, (k, img) in enumerate(((0, x), (1, y))):
        sl = slice(r * n, (r + 1) * n)
        Mt[sl, k] = 1.0
        Mt[sl, 2] = -img
        bt[sl] = -(RX[:, k] - img * RX[:, 2])
    t = np.linalg.lstsq(Mt, bt, rcond=None)[0]
    return R, np.asarray(t, dtype=np.float64)


def reprojection_cost(X: F64, xy: F64, R: F64, t: F64) -> float:
    """Sum of squared reprojection errors in normalized coordinates (points behind the camera: inf)."""
    P = X @ R.T + t
    if np.any(P[:, 2] <= 0):
        return float("inf")
    e = P[:, :2] / P[:, 2:3] - xy
    return float(np.sum(e * e))


def rpnp(points_m: ArrayLike, xy_normalized: ArrayLike) -> list[tuple[F64, F64, float]]:
    """RPnP candidates ``(R, t, cost)`` for ``x_cam = R X + t``, best (lowest cost) first.

    ``xy_normalized`` are ideal (undistorted) normalized image coordinates. Raises RPnPError for
    fewer than 4 points or collinear points.
    """
    X = np.asarray(points_m, dtype=np.float64)
    xy = np.asarray(xy_normalized, dtype=np.float64)
    _check(X, xy)
    # Centre and scale the target for conditioning; undone on the translation at the end.
    centre = X.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((X - centre) ** 2, axis=1))))
    Xs = (X - centre) / scale
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    a, b = _axis_pair(xy)
    d_ab2 = float(np.sum((Xs[b] - Xs[a]) ** 2))
    if d_ab2 < 1e-18:
        raise RPnPError("two target points coincide; each target point must be distinct")
    z_obj = (Xs[b] - Xs[a]) / np.sqrt(d_ab2)
    c_ab = float(rays[a] @ rays[b])
    P = np.polynomial.polynomial
    others = np.array([j for j in range(len(X)) if j not in (a, b)])
    off_axis = np.linalg.norm(np.cross(Xs[others] - Xs[a], z_obj), axis=1)
    others = others[off_axis >= 1e-6]  # on the axis: a subset without information about u
    if others.size == 0:
        raise RPnPError("all other target points lie on the line through the axis pair; the points are collinear")
    f = _quartics(c_ab, rays[others] @ rays[a], rays[others] @ rays[b],
                  np.sum((Xs[others] - Xs[a]) ** 2, axis=1) / d_ab2, np.sum((Xs[others] - Xs[b]) ** 2, axis=1) / d_ab2)
    f /= np.maximum(np.max(np.abs(f), axis=1, keepdims=True), 1e-300)  # every subset on one scale
    F = np.zeros(9)  # sum of f_j^2, lowest power first
    for i in range(5):
        for k in range(5):
            F[i + k] += float(f[:, i] @ f[:, k])
    dF = P.polyder(F)
    roots = np.roots(dF[::-1]) if np.any(dF) else np.array([1.0])
    real = roots[np.abs(roots.imag) <= 1e-6 * np.maximum(1.0, np.abs(roots.real))].real
    ddF = P.polyder(dF)
    cands: list[tuple[F64, F64, float]] = []
    for u0 in real[real > 0]:
        u = float(u0)
        for _ in range(3):  # Newton polish: np.roots loses digits on clustered roots
            slope = float(P.polyval(u, ddF))
            if slope == 0.0:
                break
            step = float(P.polyval(u, dF)) / slope
            if not np.isfinite(step) or abs(step) > 0.1 * abs(u):
                break
            u -= step
        q = 1.0 + u * u - 2.0 * u * c_ab
        if q <= 1e-15:
            continue
        ta = np.sqrt(d_ab2 / q)
        Qa, Qb = ta * rays[a], u * ta * rays[b]
        axis = Qb - Qa
        z_cam = axis / np.linalg.norm(axis)
        R, ts = _pose_about_axis(Xs, xy, z_obj, z_cam)
        t = scale * ts - R @ centre
        cands.append((R, t, reprojection_cost(X, xy, R, t)))
    if not cands:
        raise RPnPError("no RPnP solution with the points in front of the camera (degenerate configuration?)")
    cands.sort(key=lambda c: c[2])
    return cands
