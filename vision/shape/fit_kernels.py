"""Compiled Gauss-Newton loops of the shape matcher's least-squares refinement (numba).

Each loop is one call over the model points (the numpy versions spent most of their time in call
overhead: a dozen array operations per step on a few hundred points). Poses are (x, y, theta[,
scale]) in pixels of the crop being fitted and radians; model points and normals are relative to
the reference point (level pixels). The edge measurements they iterate on (``associate``,
``profile_centroids``) are in ``kernels``. Compiled on first use and cached on disk
(``cache=True``); ``warmup.warm_up`` loads them.

- ``gn_normal_equations``: the 4x4 normal equations of one weighted Gauss-Newton step.
- ``gn_step``: that step solved (the two fit stages' shared solve).
- ``fit_stage_a``: the Gauss-Newton loop of the refinement on gradient peaks.
- ``fit_stage_b``: the refinement's Gauss-Newton loop on centroid edge positions (level 0).
- ``perspective_fit``: the final plane-homography fit on centroid edge positions.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vision.shape import small_kernels
from vision.shape.kernels import associate, profile_centroids
from vision.shape.small_kernels import compiled

F64 = NDArray[np.float64]


@compiled(inline="always")  # one call site (gn_step): compiled there only
def gn_normal_equations(n: F64, Rm: F64, Rdm: F64, scale: float, wgt: F64, resid: F64
                        ) -> tuple[F64, F64]:
    """``A = J^T W J`` and ``b = J^T W r`` for (x, y, theta, scale) on normal distances."""
    A = np.zeros((4, 4), np.float64)
    b = np.zeros(4)
    J = np.empty(4)
    for i in range(n.shape[0]):
        w = wgt[i]
        if w == 0.0:
            continue
        J[0] = n[i, 0]
        J[1] = n[i, 1]
        J[2] = scale * (n[i, 0] * Rdm[i, 0] + n[i, 1] * Rdm[i, 1])
        J[3] = n[i, 0] * Rm[i, 0] + n[i, 1] * Rm[i, 1]
        for r in range(4):
            b[r] += J[r] * w * resid[i]
            for c in range(4):
                A[r, c] += J[r] * w * J[c]
    return A, b


@compiled()  # not inlined: the two fit stages share one compiled copy
def gn_step(n: F64, Rm: F64, Rdm: F64, scale: float, wgt: F64, resid: F64, k: int) -> tuple[F64, bool]:
    """One Gauss-Newton step of (x, y, theta[, scale]) (``k`` 3 or 4) on normal distances ``resid``:
    ``gn_normal_equations``' leading ``k`` x ``k`` system, its diagonal raised by 1e-9, solved.
    Returns the step and ``ok`` (False: a zero pivot, the step undefined)."""
    A, b = gn_normal_equations(n, Rm, Rdm, scale, wgt, resid)
    Ak = np.empty((k, k), np.float64)
    bk = np.empty(k)
    for j in range(k):  # loops, not slice copies (each compiles its shape checks)
        bk[j] = b[j]
        for c in range(k):
            Ak[j, c] = A[j, c]
        Ak[j, j] += 1e-9
    return small_kernels.solve(Ak, bk)


@compiled()
def fit_stage_a(G: NDArray[np.float32], m: F64, nrm: F64, pose: F64, s0: float, max_scale_dev: float,
                search_px: float, iterations: int, thr: float, reject_below: float, fit_scale: bool,
                radius: float, vis_margin: float, width: float, height: float
                ) -> tuple[F64, bool, F64, F64, NDArray[np.bool_], F64, F64]:
    """The Gauss-Newton loop of ``refine.refine_lsq`` on gradient peaks, in one call.

    ``pose`` = (x, y, theta, scale) in crop pixels, updated; returns (pose, failed, q, d, found,
    cosd, sign) of the last association (``q``: the model points at the pose they were associated
    at). Points outside ``[vis_margin, size - 1 - vis_margin]`` take no part. Tukey weights with a
    cut-off that shrinks with the search range; a step moving the outermost point < 0.02 px ends it.
    """
    npts = m.shape[0]
    x, y, th, sc = pose[0], pose[1], pose[2], pose[3]
    rng = search_px
    q = np.zeros((npts, 2), np.float64)
    n = np.zeros((npts, 2), np.float64)
    Rm = np.zeros((npts, 2), np.float64)
    Rdm = np.zeros((npts, 2), np.float64)
    wgt = np.zeros(npts)
    d = np.zeros(npts)
    found = np.empty(npts, np.bool_)
    cosd = np.zeros(npts)
    sign = np.empty(npts)
    for i in range(npts):  # no edge found, sign 1 (loops: np.zeros of bool and np.ones compile their own)
        found[i] = False
        sign[i] = 1.0
    failed = False
    for it in range(iterations):
        c, s = math.cos(th), math.sin(th)
        for i in range(npts):
            mx, my = m[i, 0], m[i, 1]
            Rm[i, 0] = c * mx + s * my
            Rm[i, 1] = -s * mx + c * my
            Rdm[i, 0] = c * my - s * mx  # R (m_y, -m_x)
            Rdm[i, 1] = -s * my - c * mx
            q[i, 0] = sc * Rm[i, 0] + x
            q[i, 1] = sc * Rm[i, 1] + y
            n[i, 0] = c * nrm[i, 0] + s * nrm[i, 1]
            n[i, 1] = -s * nrm[i, 0] + c * nrm[i, 1]
        d, found, cosd, sign = associate(G, q, n, int(math.ceil(rng)), thr)
        cut = max(rng * 0.75, 1.0)
        wsum = 0.0
        nfound = 0
        for i in range(npts):
            if found[i] and not (vis_margin <= q[i, 0] <= width - vis_margin
                                 and vis_margin <= q[i, 1] <= height - vis_margin):
                found[i] = False
            w = 0.0
            if found[i]:
                nfound += 1
                if abs(d[i]) < cut:
                    r = d[i] / cut
                    w = (1 - r * r) ** 2
            wgt[i] = w
            wsum += w
        if wsum < 6 or (it == 0 and nfound < reject_below * npts):
            failed = True
            break
        k = 4 if (fit_scale and (it > 0 or iterations == 1)) else 3
        delta, ok = gn_step(n, Rm, Rdm, sc, wgt, d, k)
        if not ok:
            failed = True
            break
        ds = delta[3] if k == 4 else 0.0
        x += delta[0]
        y += delta[1]
        th += delta[2]
        sc = min(max(sc + ds, s0 * (1 - max_scale_dev)), s0 * (1 + max_scale_dev))
        moved = abs(delta[0]) + abs(delta[1]) + (abs(delta[2]) + abs(ds)) * radius
        rng = max(rng * 0.6, 1.5)
        if moved < 0.02:
            break
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = x, y, th, sc
    return out, failed, q, d, found, cosd, sign


@compiled()
def perspective_fit(img_f: NDArray[np.float32], m: F64, nrm: F64, x: float, y: float, th: float, sc: float,
                    min_contrast: float, half: int) -> tuple[float, float, float, float]:
    """``refine._perspective_fit`` in one call (the same arithmetic, no numpy temporaries): a
    similarity refined to a plane homography ``q = (A m + c) / (1 + p.m)`` by Gauss-Newton on the
    centroid normal distances (``half``: the profile's half width). Returns the reference point
    ``c`` (crop pixels) and the angle (rad) and scale of the local linear map ``A - c p^T``."""
    npts = m.shape[0]
    co, si = math.cos(th), math.sin(th)
    a00, a01, a10, a11 = sc * co, sc * si, -sc * si, sc * co
    c0, c1 = x, y
    p0, p1 = 0.0, 0.0
    q = np.empty((npts, 2), np.float64)
    n = np.empty((npts, 2), np.float64)
    w = np.empty(npts)
    J = np.empty((npts, 8), np.float64)
    for _ in range(2):
        l00, l01, l10, l11 = a00 - c0 * p0, a01 - c0 * p1, a10 - c1 * p0, a11 - c1 * p1
        for i in range(npts):
            mx, my = m[i, 0], m[i, 1]
            wi = 1.0 + (mx * p0 + my * p1)
            w[i] = wi
            q[i, 0] = (mx * a00 + my * a01 + c0) / wi
            q[i, 1] = (mx * a10 + my * a11 + c1) / wi
            nx = nrm[i, 0] * l00 + nrm[i, 1] * l01
            ny = nrm[i, 0] * l10 + nrm[i, 1] * l11
            nn = max(math.sqrt(nx * nx + ny * ny), 1e-12)
            n[i, 0] = nx / nn
            n[i, 1] = ny / nn
        off, S, clean = profile_centroids(img_f, q, n, half)
        H = np.zeros((8, 8), np.float64)
        g = np.zeros(8)
        nw = 0
        jmax = 0.0
        for i in range(npts):
            ok = clean[i] and abs(off[i]) < 1.0 and abs(S[i]) >= 0.5 * min_contrast
            wt = (1 - off[i] ** 2) ** 2 if ok else 0.0
            mx, my = m[i, 0] / w[i], m[i, 1] / w[i]
            inv = 1.0 / w[i]
            nx, ny = n[i, 0], n[i, 1]
            qn = nx * q[i, 0] + ny * q[i, 1]
            J[i, 0] = nx * mx
            J[i, 1] = nx * my
            J[i, 2] = nx * inv
            J[i, 3] = ny * mx
            J[i, 4] = ny * my
            J[i, 5] = ny * inv
            J[i, 6] = -qn * mx
            J[i, 7] = -qn * my
            for k in range(8):
                jmax = max(jmax, abs(J[i, k]))
            if wt == 0.0:
                continue
            nw += 1
            for r in range(8):
                g[r] += J[i, r] * (wt * off[i])
                for k in range(r, 8):  # the upper triangle (mirrored below): half the code to compile
                    H[r, k] += J[i, r] * (J[i, k] * wt)
        if nw < 20:
            break
        for r in range(8):
            for k in range(r):
                H[r, k] = H[k, r]
        for k in range(8):
            H[k, k] += 1e-9 * (1 + jmax)
        delta, ok = small_kernels.solve(H, g)
        if not ok:
            break
        a00 += delta[0]
        a01 += delta[1]
        a10 += delta[3]
        a11 += delta[4]
        c0 += delta[2]
        c1 += delta[5]
        p0 += delta[6]
        p1 += delta[7]
        if abs(delta[2]) + abs(delta[5]) < 1e-4:
            break
    l00, l10, l11, l01 = a00 - c0 * p0, a10 - c1 * p0, a11 - c1 * p1, a01 - c0 * p1
    theta = math.atan2(-l10, l00)
    scale = math.sqrt(abs(l00 * l11 - l01 * l10))
    return c0, c1, theta, scale


@compiled()
def fit_stage_b(img_f: NDArray[np.float32], m: F64, nrm: F64, x: float, y: float, th: float, sc: float,
                s0: float, max_scale_dev: float, min_contrast: float, fit_scale: bool, iterations: int,
                radius: float, vis_margin: float, width: float, height: float, half: int
                ) -> tuple[float, float, float, float]:
    """The centroid stage of ``refine.refine_lsq`` in one call: up to ``iterations`` weighted
    Gauss-Newton steps on (x, y, theta[, scale]) of the centroid edge offsets along the normals of
    the raw crop ``img_f`` (profile half width ``half``), the same arithmetic as the numpy loop.
    Points outside ``[vis_margin, size - vis_margin]`` take no part; a step moving the outermost
    point < 0.001 px ends it. Returns the pose (crop pixels, rad)."""
    npts = m.shape[0]
    q = np.empty((npts, 2), np.float64)
    n = np.empty((npts, 2), np.float64)
    Rm = np.empty((npts, 2), np.float64)
    Rdm = np.empty((npts, 2), np.float64)
    wgt = np.empty(npts)
    for _ in range(iterations):
        c, s = math.cos(th), math.sin(th)
        for i in range(npts):
            mx, my = m[i, 0], m[i, 1]
            Rm[i, 0] = mx * c + my * s
            Rm[i, 1] = mx * -s + my * c
            Rdm[i, 0] = my * c + (-mx) * s  # R (m_y, -m_x)
            Rdm[i, 1] = my * -s + (-mx) * c
            q[i, 0] = sc * Rm[i, 0] + x
            q[i, 1] = sc * Rm[i, 1] + y
            n[i, 0] = nrm[i, 0] * c + nrm[i, 1] * s
            n[i, 1] = nrm[i, 0] * -s + nrm[i, 1] * c
        off, S, clean = profile_centroids(img_f, q, n, half)
        wsum = 0.0
        for i in range(npts):
            ok = (clean[i] and abs(off[i]) < 1.0 and abs(S[i]) >= 0.5 * min_contrast
                  and vis_margin <= q[i, 0] <= width - vis_margin and vis_margin <= q[i, 1] <= height - vis_margin)
            wgt[i] = (1 - off[i] ** 2) ** 2 if ok else 0.0
            wsum += wgt[i]
        if wsum < 6:
            break
        delta, ok = gn_step(n, Rm, Rdm, sc, wgt, off, 4 if fit_scale else 3)
        if not ok:
            break
        ds = delta[3] if fit_scale else 0.0
        x += delta[0]
        y += delta[1]
        th += delta[2]
        sc = min(max(sc + ds, s0 * (1 - max_scale_dev)), s0 * (1 + max_scale_dev))
        if abs(delta[0]) + abs(delta[1]) + (abs(delta[2]) + abs(ds)) * radius < 1e-3:
            break
    return x, y, th, sc
