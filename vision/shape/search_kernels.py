"""Compiled loops of the discrete search (numba): the top level's score planes and local maxima,
and the neighbourhood tracking down the pyramid.

- ``accumulate_top``: LINE-MOD's linearised memories — each feature's shifted response map is one
  contiguous run of the padded map, so a rotated template's score plane is a sum of runs. numpy
  did one ``np.add`` call per feature and angle (call overhead and a read-modify-write of the plane
  each time); here the same uint8 sums are one compiled, vectorised loop adding four runs per pass
  (5x less time, the same numbers).
- ``response_planes``: the orientation response maps from the quantised orientations, one pass.
- ``top_maxima``: local maxima over position and angle (3x3x3, circular in angle over the full turn)
  of the score planes at or above a threshold, from each plane's 3x3 maximum (``cv2.dilate``) in one
  pass (was a dozen whole-array numpy passes).
- ``spread_budget``: the best candidates under a per-position budget, so that a few strong parts (each
  a cluster of maxima at neighbouring positions and angles) cannot take the whole candidate list.
- ``track_batch``: the best pose of each candidate over +-reach px and +-n_steps angle steps on a
  response map (``responses.track``'s contract), the feature offsets rotated inside the loop. A
  candidate whose rotated model stays inside the map takes a path without bounds checks.
- ``run_sizes``: the size of each evidenced point's run, linked along the model's chains (union-find;
  the verification's ``surround`` drops specks by it; scipy's graph components cost 10x more).

Compiled on first use and cached on disk (``cache=True``); ``warmup.warm_up`` loads them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vision.shape.small_kernels import compiled

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


@compiled(boundscheck=False)
def accumulate_top(padf: U8, b: I64, start: I64, run: int, lin: U8, a0: int, a1: int) -> None:
    """Add up the score planes of angles ``a0 .. a1 - 1`` into ``lin`` (angle, run) in place:
    ``lin[a, i] = sum_f padf[b[a, f], start[a, f] + i]`` for ``i < run`` (uint8, no overflow while
    4 * features < 256)."""
    nf = b.shape[1]
    for ai in range(a0, a1):
        acc = lin[ai, :run]
        k = 0
        while k + 4 <= nf:  # four runs per pass over the plane: a quarter of its loads and stores
            s0 = padf[b[ai, k], start[ai, k]:start[ai, k] + run]
            s1 = padf[b[ai, k + 1], start[ai, k + 1]:start[ai, k + 1] + run]
            s2 = padf[b[ai, k + 2], start[ai, k + 2]:start[ai, k + 2] + run]
            s3 = padf[b[ai, k + 3], start[ai, k + 3]:start[ai, k + 3] + run]
            for i in range(run):
                acc[i] += s0[i] + s1[i] + s2[i] + s3[i]
            k += 4
        while k < nf:
            s0 = padf[b[ai, k], start[ai, k]:start[ai, k] + run]
            for i in range(run):
                acc[i] += s0[i]
            k += 1


@compiled(boundscheck=False)
def response_planes(q: U8, gx: NDArray[np.float32], gy: NDArray[np.float32], thr: float, table: U8,
                    out: U8) -> None:
    """``out[b] = table[b, q]`` for every bin b, with ``q`` taken as "no edge" (the table's last
    column) where the gradient's magnitude is below ``thr``: the orientation response maps in one
    pass. The magnitude is ``vision.image.magnitude``'s, to the bit: the float32 square root of the
    float32 sum of the float32 squares (IEEE operations, the same at any alignment)."""
    h, w = q.shape
    none = table.shape[1] - 1
    qq = np.empty((h, w), np.uint8)
    for y in range(h):
        for x in range(w):
            m = np.sqrt(gx[y, x] * gx[y, x] + gy[y, x] * gy[y, x])
            qq[y, x] = none if m < thr else q[y, x]
    for b in range(table.shape[0]):
        tb = table[b]
        ob = out[b]
        for y in range(h):
            for x in range(w):
                ob[y, x] = tb[qq[y, x]]


@compiled(boundscheck=False)
def top_maxima(planes: U8, dil: U8, nh: int, thr: int, circular: bool) -> tuple[I64, I64, I64, I64]:
    """Cells of the score ``planes`` (A, rows, cols; only rows < ``nh`` and the columns of ``dil`` count)
    scoring >= ``thr`` and >= ``dil`` (A, rows, columns: each plane's 3x3 maximum) of their own plane and
    of the planes of the next and previous angle (wrapping round when ``circular``): local maxima over
    position and angle. ``planes`` may be wider than ``dil`` (the accumulator's rows, whose columns past
    ``dil``'s are not looked at: no copy of the planes' columns is made). Returns (angle index, row,
    column, score) in (angle, row, column) order."""
    na = planes.shape[0]
    nw = dil.shape[2]
    cap = 1024
    out = np.empty((4, cap), np.int64)
    n = 0
    for a in range(na):
        am = a - 1 if a > 0 else (na - 1 if circular else -1)
        ap = a + 1 if a < na - 1 else (0 if circular else -1)
        for y in range(nh):
            row = planes[a, y]
            mx = 0
            for x in range(nw):  # a max reduction vectorises; about half the rows reach no threshold
                mx = max(mx, row[x])
            if mx < thr:
                continue
            for x in range(nw):
                v = row[x]
                if v < thr or v < dil[a, y, x]:
                    continue
                if am >= 0 and v < dil[am, y, x]:
                    continue
                if ap >= 0 and v < dil[ap, y, x]:
                    continue
                if n == cap:
                    cap *= 2
                    grown = np.empty((4, cap), np.int64)
                    for r in range(4):  # a loop: a slice copy compiles a shape-error message
                        for j in range(n):
                            grown[r, j] = out[r, j]
                    out = grown
                out[0, n] = a
                out[1, n] = y
                out[2, n] = x
                out[3, n] = v
                n += 1
    return out[0, :n], out[1, :n], out[2, :n], out[3, :n]


@compiled(boundscheck=False)
def track_batch(resp: U8, m: F64, phi0: F64, cx: I64, cy: I64, cos_t: F64, sin_t: F64, thetas: F64,
                scale: F64, reach: int, bin_w: float) -> tuple[F64, F64, F64, F64]:
    """Best pose of each candidate c over positions ``cx, cy`` +-``reach`` px and the angles
    ``thetas[c]`` (cosines and sines given): (x, y, theta, score) each.

    ``m``: (F, 2) feature offsets (level pixels), ``phi0``: their normals' angles (rad). A feature
    at angle theta sits at ``rint(k R(theta) m)`` and looks up the response map of its normal's
    orientation bin; features outside the map score 0. Ties go to the angle nearest the middle one,
    and the position is the centre of the best angle's plateau of equal scores.
    """
    nb, h, w = resp.shape
    nc, na = thetas.shape
    nf = m.shape[0]
    mid = (na - 1) // 2
    side = 2 * reach + 1
    npos = side * side
    flat = resp.ravel()
    plane = h * w
    xs = np.empty(nc)
    ys = np.empty(nc)
    ts = np.empty(nc)
    out = np.empty(nc)
    dx = np.empty(nf, np.int64)
    dy = np.empty(nf, np.int64)
    base = np.empty(nf, np.int64)
    sc = np.empty((na, npos), np.int64)
    inv_w = 1.0 / bin_w
    for c in range(nc):
        x0 = min(max(cx[c], 0), w - 1)
        y0 = min(max(cy[c], 0), h - 1)
        for a in range(na):
            cc = scale[c] * cos_t[c, a]
            ss = scale[c] * sin_t[c, a]
            lox, hix, loy, hiy = w, -1, h, -1
            for f in range(nf):
                ddx = np.int64(np.rint(cc * m[f, 0] + ss * m[f, 1]))
                ddy = np.int64(np.rint(-ss * m[f, 0] + cc * m[f, 1]))
                dx[f] = ddx
                dy[f] = ddy
                # the bin of (phi0 - theta) mod pi: pi is nb bins, so an integer modulo does it (an
                # fmod per feature was half of this loop's time)
                bi = np.int64(math.floor((phi0[f] - thetas[c, a]) * inv_w)) % nb
                base[f] = bi * plane + (y0 + ddy) * w + x0 + ddx
                lox = min(lox, x0 + ddx)
                hix = max(hix, x0 + ddx)
                loy = min(loy, y0 + ddy)
                hiy = max(hiy, y0 + ddy)
            inside = lox - reach >= 0 and loy - reach >= 0 and hix + reach < w and hiy + reach < h
            p = 0
            for oy in range(-reach, reach + 1):
                for ox in range(-reach, reach + 1):
                    s = 0
                    if inside:
                        off = oy * w + ox
                        for f in range(nf):
                            s += flat[base[f] + off]
                    else:
                        for f in range(nf):
                            xx = x0 + ox + dx[f]
                            yy = y0 + oy + dy[f]
                            if 0 <= xx < w and 0 <= yy < h:
                                s += flat[base[f] + oy * w + ox]
                    sc[a, p] = s
                    p += 1
        best_a, best_p = 0, 0
        best_v = -1e30
        for a in range(na):
            tie = abs(a - mid) * 0.01
            for p in range(npos):
                v = sc[a, p] - tie
                if v > best_v:
                    best_v, best_a, best_p = v, a, p
        best = sc[best_a, best_p]
        cnt, sx, sy = 0, 0, 0
        p = 0
        for oy in range(-reach, reach + 1):
            for ox in range(-reach, reach + 1):
                if sc[best_a, p] == best:
                    cnt += 1
                    sx += ox
                    sy += oy
                p += 1
        xs[c] = x0 + sx / cnt
        ys[c] = y0 + sy / cnt
        ts[c] = thetas[c, best_a]
        out[c] = best / (4.0 * nf)
    return xs, ys, ts, out


@compiled(boundscheck=False)
def spread_budget(xs: F64, ys: F64, sc: F64, radius: float, n_free: int, per_position: int, extra_min: float,
                  cap: int) -> I64:
    """Indices of at most ``cap`` candidates (``xs``, ``ys``, scores ``sc``, sorted best first): the
    best ``n_free`` whatever their position, then one scoring at least ``extra_min`` while its
    neighbourhood (within ``radius`` of a group's first member) holds fewer than ``per_position``."""
    n = xs.shape[0]
    m = min(n, cap)
    keep = np.empty(m, np.int64)
    gx = np.empty(m)
    gy = np.empty(m)
    gcount = np.empty(m, np.int64)  # a group's set when it opens (np.zeros of int64: one more compile)
    ng = 0
    nk = 0
    r2 = radius * radius
    for i in range(n):
        if nk == cap or (i >= n_free and sc[i] < extra_min):
            break
        g = -1
        for j in range(ng):
            if (xs[i] - gx[j]) ** 2 + (ys[i] - gy[j]) ** 2 < r2:
                g = j
                break
        if g < 0:
            g = ng
            gx[ng] = xs[i]
            gy[ng] = ys[i]
            gcount[ng] = 0
            ng += 1
        elif i >= n_free and gcount[g] >= per_position:
            continue
        gcount[g] += 1
        keep[nk] = i
        nk += 1
    return keep[:nk]


@compiled()
def run_sizes(n: int, a: I64, b: I64, ev: NDArray[np.bool_]) -> I64:
    """For each of ``n`` points, the number of points in its run: the connected component of the pairs
    ``(a[k], b[k])`` whose both ends are ``ev`` (0 where ``ev`` is false)."""
    parent = np.empty(n, np.int64)
    root = np.empty(n, np.int64)
    count = np.empty(n, np.int64)  # zeros (set here: np.zeros of int64 costs a compile of its own)
    out = np.empty(n, np.int64)
    for i in range(n):
        parent[i] = i
        count[i] = 0
    for k in range(len(a)):
        i, j = a[k], b[k]
        if not (ev[i] and ev[j]):
            continue
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        while parent[j] != j:
            parent[j] = parent[parent[j]]
            j = parent[j]
        if i != j:
            if i < j:
                parent[j] = i
            else:
                parent[i] = j
    for i in range(n):
        r = i
        while parent[r] != r:
            r = parent[r]
        root[i] = r
        if ev[i]:
            count[r] += 1
    for i in range(n):
        out[i] = count[root[i]] if ev[i] else 0
    return out


def warm_up() -> None:
    """Load (or compile) this module's kernels on tiny inputs (see ``warmup.warm_up``)."""
    z8 = np.zeros((1, 8), np.uint8)
    zi = np.zeros((1, 1), np.int64)
    accumulate_top(z8, zi, zi, 1, z8.copy(), 0, 1)
    z2 = np.zeros((2, 2), np.uint8)
    f2 = np.zeros((2, 2), np.float32)
    response_planes(z2, f2, f2, 1.0, np.zeros((8, 33), np.uint8), np.zeros((8, 2, 2), np.uint8))
    p3 = np.zeros((1, 2, 2), np.uint8)
    top_maxima(p3, p3, 1, 1, False)
    spread_budget(np.zeros(2), np.zeros(2), np.zeros(2), 1.0, 1, 1, 0.0, 2)
    z1 = np.zeros(1, np.int64)
    t = np.zeros((1, 1))
    track_batch(p3, np.zeros((1, 2)), np.zeros(1), z1, z1, t, t, t, np.ones(1), 0, math.pi / 8)
    run_sizes(1, z1, z1, np.ones(1, np.bool_))
