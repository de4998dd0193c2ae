"""Compiled inner loops of the shape matcher (numba): one pass over the model points each.

The numpy versions spend most of their time in call overhead on a few hundred points (a dozen
array operations per Gauss-Newton step); these loops do the same arithmetic per point in one
call. Sampling follows ``vision.image.bilinear`` exactly (pixel centres at integers, clamped at
the border). Compiled on first use and cached on disk (``cache=True``).

- ``associate``: nearest image edge of matching orientation along each model normal.
- ``gn_normal_equations``: the 4x4 normal equations of one weighted Gauss-Newton step.
- ``gn_step``: that step solved (the two fit stages' shared solve).
- ``profile_centroids``: the centroid edge offset, contrast and cleanliness of each normal profile.
- ``fit_stage_a``: the Gauss-Newton loop of the refinement on gradient peaks.
- ``fit_stage_b``: the refinement's Gauss-Newton loop on centroid edge positions (level 0).
- ``perspective_fit``: the final plane-homography fit on centroid edge positions.

The discrete search's loops are in ``search_kernels``.
"""

from __future__ import annotations

import math
import threading

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


_WARM = threading.Event()
_WARM_LOCK = threading.Lock()


def warm_up(image_size: tuple[int, int] | None = None) -> None:
    """Load (or compile) every kernel now, on tiny inputs, once per process: the first search then
    costs what the next ones cost. Loading the compiled code from numba's disk cache takes ~1 s;
    compiling it on a cold cache ~20 s. Thread-safe: a second caller waits for the first; later
    calls return at once. ``search.find`` calls it before its clock starts, so a search's
    ``timeout_s`` never pays for it. ``image_size`` ``(width, height)``: the images the searches
    will see (default 320x240); the warm-up's own small search runs on one that size, so the
    process's memory for such images is in place before the first timed search."""
    if _WARM.is_set():
        return
    with _WARM_LOCK:
        if not _WARM.is_set():
            _load_all()
            _WARM.set()  # before the search below, which calls warm_up() itself
            _first_search(image_size or (320, 240))


def _first_search(image_size: tuple[int, int]) -> None:
    """One small real search (teach a drawn part, find it turned): loads whatever compiled loop a
    search reaches that ``_load_all`` does not name, and pays the first call's one-off costs on the
    rest of the path (refinement, verification; first touches of image-sized buffers), so the next
    search costs what the hundredth does."""
    import cv2

    from vision.shape.model import teach
    from vision.shape.search import find

    w, h = max(int(image_size[0]), 320), max(int(image_size[1]), 240)
    img = np.full((h, w), 60, np.uint8)
    part = np.array([[110, 70], [210, 70], [210, 110], [160, 110], [160, 170], [110, 170]], np.int32)
    cv2.fillPoly(img, [part], 190)
    cv2.circle(img, (135, 95), 10, 60, -1)
    img = cv2.GaussianBlur(img, (5, 5), 0.8)
    model = teach(img, (90.0, 50.0, 140.0, 140.0))
    M = cv2.getRotationMatrix2D((160.0, 120.0), 25.0, 1.0)
    M[:, 2] += (7.3, -4.6)
    find(model, cv2.warpAffine(img, M, (w, h), borderValue=60))


def _load_all() -> None:
    z2 = np.zeros((2, 2))
    associate(np.zeros((4, 4, 2), np.float32), z2, z2, 1, 1.0)
    profile_centroids(np.zeros((4, 4), np.float32), z2, z2, 1)
    fit_stage_a(np.zeros((4, 4, 2), np.float32), z2, z2, np.zeros(4), 1.0, 0.1, 1.0, 1, 1.0, 0.0, False, 1.0,
                0.0, 4.0, 4.0)
    perspective_fit(np.zeros((4, 4), np.float32), z2, z2, 0.0, 0.0, 0.0, 1.0, 1.0, 1)
    percentile75(magnitudes(np.zeros((4, 4, 2), np.float32), z2))
    fit_stage_b(np.zeros((4, 4), np.float32), z2, z2, 0.0, 0.0, 0.0, 1.0, 1.0, 0.1, 1.0, True, 1, 1.0, 0.0, 4.0,
                4.0, 1)
    from vision.shape import score, search_kernels
    search_kernels.warm_up()
    score.point_agreement(np.zeros((4, 4, 2), np.float32), z2, z2, 1.0, 1.5, 0.75, 0.5, 0.25)
    for sigma in (0.0, 1.0):  # the score's noise reference per smoothing, computed once per process
        score.find_threshold(np.zeros((8, 8), np.uint8), sigma, 3.0, 0.0)


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
