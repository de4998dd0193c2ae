"""HALCON-style circle plate detection: our own (OpenCV has no detector for framed, oriented plates).

Geometry (shared/INTERFACES.md §2, ``calibration.targets.CirclePlate``): black marks on white, a
black frame whose inner edge lies one pitch outside the outer mark centres, and a black right
triangle in the frame's inner corner nearest mark (0, 0).

Steps:

1. Segment dark regions (Otsu, then a local-mean threshold for uneven light), and look for a
   dark region with a bright hole holding mark-like blobs: the frame and its marks.
2. The frame's inner edge gives four lines and corners; every way of laying the target's
   corners on them (four turns, and the mirror images for mirrored views) predicts the mark
   grid through a homography, refined on the matched marks. The hypothesis matching the most
   marks wins; too few matched marks, or more blobs than marks, is a "mark count mismatch".
3. The orientation triangle is read by sampling the four inner frame corners: exactly one must
   be dark (else "orientation unreadable"); it is the target's corner (-pitch, -pitch), so ids
   follow the plate, never the image. A square plate in a *mirrored* image (not a real camera)
   cannot be told from its transpose; we assume the printed side faces the camera.
4. Each mark's edge is located with sub-pixel precision along rays from its centre (the
   crossing of the half-way grey level between the local dark and light levels of each ray, so
   uneven light does not shift it); a direct least-squares ellipse (Fitzgibbon/Halir-Flusser)
   is fitted to those edge points, with outlier rejection (partly hidden marks are dropped).
5. Perspective bias (Heikkilä, PAMI 2000): the imaged ellipse's centre is not the image of the
   mark's centre. The plate-to-image mapping is modelled around each mark from its grid
   neighbours (Gaussian-weighted: a homography plus a quadratic correction, so that lens
   distortion is followed too), the mark's rim is mapped through it and fitted with an ellipse, and (ellipse centre -
   mapped centre) is subtracted; twice, refitting on the corrected centres. ``Detection.uv``
   holds the corrected centres, ``uv_ellipse`` the raw ellipse centres.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.observations import Detection
from calibration.targets import CirclePlate

FloatArray = NDArray[np.float64]

EDGE_SMOOTH_SIGMA_PX = 1.0
"""Gaussian smoothing before the edge rays are sampled: bilinear sampling of very sharp edges
otherwise leaves a systematic ~0.01 px centre error; a symmetric blur does not move a centre."""

TRIANGLE_INSET = 0.5 / (2.0 + np.sqrt(2.0))
"""Incentre of the orientation triangle, from the frame's inner corner along both legs, in pitches."""


@dataclass
class _Frame:
    corners: FloatArray  # (4, 2) inner frame corners, clockwise on screen
    marks: FloatArray  # (n, 2) coarse mark centres inside the frame
    ellipses: list[tuple[tuple[float, float], tuple[float, float], float]]


@dataclass
class _Failure:
    stage: int  # how far the attempt got: 0 no frame, 1 count mismatch, 2 orientation
    reason: str


# ---------------------------------------------------------------------------------------------
# segmentation


def _binarizations(grey: NDArray[np.uint8]) -> Iterator[NDArray[np.uint8]]:
    """Dark-is-255 masks to try in order: global Otsu, then local mean thresholds (uneven light)."""
    smooth = cv2.GaussianBlur(grey, (5, 5), 0)
    _, otsu = cv2.threshold(smooth, 0, 255, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    yield otsu
    h, w = grey.shape
    for frac in (0.25, 0.08):
        block = max(int(min(h, w) * frac) | 1, 31)
        yield cv2.adaptiveThreshold(smooth, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, block, 10)


def _mark_like(contour: NDArray[np.int32]) -> tuple[tuple[float, float], tuple[float, float], float] | None:
    if len(contour) < 6:
        return None
    area = cv2.contourArea(contour)
    if area < 12:
        return None
    ell = cv2.fitEllipse(contour)
    (_, _), (a, b), _ = ell
    if a <= 2 or b <= 2:
        return None
    ell_area = np.pi * a * b / 4
    if not 0.8 < area / ell_area < 1.2:
        return None
    hull_area = cv2.contourArea(cv2.convexHull(contour))
    if hull_area <= 0 or area / hull_area < 0.93:
        return None
    return ell


def _frames(binary: NDArray[np.uint8]) -> list[_Frame]:
    """Candidate frames: dark regions with a large bright hole containing mark-like blobs."""
    contours, hier = cv2.findContours(binary, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
    if hier is None:
        return []
    h = hier[0]
    frames = []
    for j in range(len(contours)):
        parent = h[j][3]
        if parent < 0:
            continue
        # j is a hole (a bright region's boundary inside a dark one) if its depth is odd.
        depth, p = 0, parent
        while p >= 0:
            depth += 1
            p = h[p][3]
        if depth % 2 == 0:
            continue
        hole = contours[j]
        hole_area = cv2.contourArea(hole)
        if hole_area < 400:
            continue
        marks, ells = [], []
        k = h[j][2]
        while k >= 0:
            ell = _mark_like(contours[k])
            if ell is not None:
                marks.append(ell[0])
                ells.append(ell)
            k = h[k][0]
        if len(marks) < 4:
            continue
        quad = _quad(hole)
        if quad is None:
            continue
        frames.append(_Frame(quad, np.asarray(marks, dtype=np.float64), ells))
    frames.sort(key=lambda f: -len(f.marks))
    return frames


def _quad(hole: NDArray[np.int32]) -> FloatArray | None:
    """Four inner frame corners (clockwise on screen) from line fits to the hole's sides."""
    hull = cv2.convexHull(hole)
    peri = cv2.arcLength(hull, True)
    approx = cv2.approxPolyDP(hull, 0.02 * peri, True).reshape(-1, 2).astype(np.float64)
    while len(approx) > 4:
        # drop the vertex whose removal loses the least area
        n = len(approx)
        loss = []
        for i in range(n):
            a, b, c = approx[i - 1], approx[i], approx[(i + 1) % n]
            loss.append(abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])))
        approx = np.delete(approx, int(np.argmin(loss)), axis=0)
    if len(approx) != 4:
        return None
    pts = hole.reshape(-1, 2).astype(np.float64)
    lines = []
    for i in range(4):
        a, b = approx[i], approx[(i + 1) % 4]
        d = b - a
        length = float(np.hypot(*d))
        if length < 8:
            return None
        t = ((pts - a) @ d) / length**2
        nrm = np.array([-d[1], d[0]]) / length
        dist = np.abs((pts - a) @ nrm)
        sel = pts[(t > 0.2) & (t < 0.8) & (dist < 0.05 * length + 2)]
        if len(sel) < 5:
            return None
        vx, vy, x0, y0 = cv2.fitLine(sel.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], dtype=np.float64), np.array([vx, vy], dtype=np.float64)))
    corners = []
    for i in range(4):
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        A = np.column_stack([d1, -d2])
        if abs(np.linalg.det(A)) < 1e-9:
            return None
        s = np.linalg.solve(A, p2 - p1)
        corners.append(p1 + s[0] * d1)
    Q = np.asarray(corners)
    x, y = Q[:, 0], Q[:, 1]
    signed = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if signed < 0:
        Q = Q[::-1].copy()
    return Q


# ---------------------------------------------------------------------------------------------
# grid assignment


def _apply_h(H: FloatArray, p: FloatArray) -> FloatArray:
    q = np.column_stack([p, np.ones(len(p))]) @ H.T
    return q[:, :2] / q[:, 2:3]


def _match(H: FloatArray, marks: FloatArray, cols: int, rows: int, tol: float = 0.3
           ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Marks that lie within ``tol`` pitches of a grid node under ``H`` (grid -> image), one per node.

    Returns (mark indices, node ids)."""
    g = _apply_h(np.asarray(np.linalg.inv(H), dtype=np.float64), marks)
    node = np.rint(g)
    res = np.hypot(*(g - node).T)
    ok = (res < tol) & (node[:, 0] >= 0) & (node[:, 0] < cols) & (node[:, 1] >= 0) & (node[:, 1] < rows)
    ok &= np.all(np.isfinite(g), axis=1)
    idx = np.nonzero(ok)[0]
    ids = (node[idx, 1] * cols + node[idx, 0]).astype(np.int64)
    # a node claimed twice: keep the closer mark
    order = np.lexsort((res[idx], ids))
    idx, ids = idx[order], ids[order]
    first = np.ones(len(ids), dtype=bool)
    first[1:] = ids[1:] != ids[:-1]
    return idx[first], ids[first]


def _grid_xy(ids: NDArray[np.int64], cols: int) -> FloatArray:
    return np.column_stack([ids % cols, ids // cols]).astype(np.float64)


def _fit_h(src: FloatArray, dst: FloatArray) -> FloatArray | None:
    if len(src) < 4:
        return None
    H, _ = cv2.findHomography(src, dst, 0)
    return None if H is None else np.asarray(H, dtype=np.float64)


def _assign(frame: _Frame, cols: int, rows: int, mirrored: bool
            ) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64], bool] | None:
    """Best grid hypothesis of one handedness: (H grid->image, mark indices, ids, mirrored)."""
    C, R = cols, rows
    plate = np.array([[-1, -1], [C, -1], [C, R], [-1, R]], dtype=np.float64)
    best: tuple[int, float, FloatArray, NDArray[np.int64], NDArray[np.int64], bool] | None = None
    Q = frame.corners if not mirrored else frame.corners[::-1]
    for s in range(4):
        Qs = np.roll(Q, -s, axis=0)
        H = cv2.getPerspectiveTransform(plate.astype(np.float32), Qs.astype(np.float32)).astype(np.float64)
        idx, ids = _match(H, frame.marks, C, R, 0.35)
        for _ in range(2):
            H2 = _fit_h(_grid_xy(ids, C), frame.marks[idx])
            if H2 is None:
                break
            H = H2
            idx, ids = _match(H, frame.marks, C, R, 0.3)
        # consistency of the frame with the grid: predicted inner corners vs measured ones
        pred = _apply_h(H, plate)
        pitch_px = np.median(np.hypot(*np.diff(pred, axis=0).T)) / max(C, R) if len(ids) else 1.0
        frame_err = float(np.max(np.hypot(*(pred - Qs).T))) / max(pitch_px, 1e-9)
        key = (len(ids), -frame_err)
        if best is None or key > (best[0], best[1]):
            best = (len(ids), -frame_err, H, idx, ids, mirrored)
    if best is None:
        return None
    n, neg_err, H, idx, ids, mirrored = best
    if -neg_err > 0.5:
        return None
    return H, idx, ids, mirrored


def _disc_mean(grey: NDArray[np.uint8], uv: FloatArray, radius: float) -> float:
    h, w = grey.shape
    r = max(1.0, radius)
    u0, u1 = int(np.floor(uv[0] - r)), int(np.ceil(uv[0] + r))
    v0, v1 = int(np.floor(uv[1] - r)), int(np.ceil(uv[1] + r))
    if u0 < 0 or v0 < 0 or u1 >= w or v1 >= h:
        return float("nan")
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    m = (uu - uv[0]) ** 2 + (vv - uv[1]) ** 2 <= r * r
    return float(grey[v0 : v1 + 1, u0 : u1 + 1][m].mean())


def _orientation(grey: NDArray[np.uint8], H: FloatArray, cols: int, rows: int,
                 grid_xy: FloatArray | None = None, uv: FloatArray | None = None) -> tuple[int, str]:
    """Which inner frame corner holds the triangle: 0 (-1,-1), 1 (C,-1), 2 (C,R), 3 (-1,R); -1 if unreadable.

    Each corner is probed through a homography fitted to the marks near that corner (lens
    distortion makes the plate-wide ``H`` extrapolate poorly to the frame), falling back to ``H``.
    """
    C, R = cols, rows
    e = TRIANGLE_INSET
    corners = np.array([[-1, -1], [C, -1], [C, R], [-1, R]], dtype=np.float64)
    inward = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    probes = corners + e * inward
    white = corners + 0.5 * inward  # bright plate between the frame corner and the corner mark
    dark = corners - 0.25 * inward  # on the frame itself
    Hk = []
    for k in range(4):
        Hc = None
        if grid_xy is not None and uv is not None:
            near = np.max(np.abs(grid_xy - (corners[k] + inward[k])), axis=1) <= 2
            if near.sum() >= 6:
                Hc = _fit_h(grid_xy[near], uv[near])
        Hk.append(H if Hc is None else Hc)
    scale = np.hypot(*(_apply_h(H, np.array([[0.0, 0.0], [1.0, 0.0]]))[1] - _apply_h(H, np.array([[0.0, 0.0]]))[0]))
    r = max(1.0, 0.06 * scale)
    t = []
    for k in range(4):
        p = _disc_mean(grey, _apply_h(Hk[k], probes[k : k + 1])[0], r)
        wv = _disc_mean(grey, _apply_h(Hk[k], white[k : k + 1])[0], r)
        dv = _disc_mean(grey, _apply_h(Hk[k], dark[k : k + 1])[0], r)
        if not (np.isfinite(p) and np.isfinite(wv) and np.isfinite(dv)) or wv - dv < 10:
            t.append(np.nan)
        else:
            t.append((p - dv) / (wv - dv))
    tt = np.asarray(t)
    if np.any(~np.isfinite(tt)):
        return -1, "orientation unreadable: an inner frame corner is outside the image or has no contrast"
    dark_corners = np.nonzero(tt < 0.5)[0]
    if len(dark_corners) != 1:
        return -1, (f"orientation unreadable: expected the triangle in exactly one inner frame corner, "
                    f"found it in {len(dark_corners)}")
    k = int(dark_corners[0])
    others = np.delete(tt, k)
    if tt[k] > 0.35 or np.min(others) < 0.65:
        return -1, "orientation unreadable: the orientation triangle is not clearly dark against the plate"
    return k, ""


# ---------------------------------------------------------------------------------------------
# sub-pixel ellipse fit


def _sample(img32: NDArray[np.float32], u: FloatArray, v: FloatArray) -> FloatArray:
    """Bilinear samples of ``img32`` at (u, v) (any equal shapes), through cv2.remap.

    remap quantizes positions to 1/32 px; along the ~100 rays of a mark that error is random
    and averages out far below 0.001 px.
    """
    shape = u.shape
    mu = u.reshape(-1, shape[-1]).astype(np.float32)
    mv = v.reshape(-1, shape[-1]).astype(np.float32)
    parts = [cv2.remap(img32, mu[i : i + 30000], mv[i : i + 30000], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE) for i in range(0, len(mu), 30000)]
    return np.concatenate(parts).reshape(shape).astype(np.float64)


def fit_ellipses_direct(x: FloatArray, y: FloatArray, w: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Direct least-squares ellipses (Fitzgibbon et al. 1999, Halir & Flusser's stable form), batched.

    ``x, y, w``: (n, m) points and 0/1 weights of n ellipses. Returns (n, 6) conics
    ``[a, b, c, d, e, f]`` of ``a x² + b xy + c y² + d x + e y + f = 0`` and an ok flag per ellipse.
    """
    n = x.shape[0]
    sw = np.maximum(w.sum(axis=1), 1.0)
    mx = (w * x).sum(axis=1) / sw
    my = (w * y).sum(axis=1) / sw
    s = np.sqrt((w * ((x - mx[:, None]) ** 2 + (y - my[:, None]) ** 2)).sum(axis=1) / sw)
    s = np.maximum(s, 1e-12)
    xs = (x - mx[:, None]) / s[:, None]
    ys = (y - my[:, None]) / s[:, None]
    D1 = np.stack([xs * xs, xs * ys, ys * ys], axis=2)
    D2 = np.stack([xs, ys, np.ones_like(xs)], axis=2)
    D1w, D2w = D1 * w[:, :, None], D2 * w[:, :, None]
    S1 = np.einsum("nmi,nmj->nij", D1w, D1)
    S2 = np.einsum("nmi,nmj->nij", D1w, D2)
    S3 = np.einsum("nmi,nmj->nij", D2w, D2)
    ok = (w.sum(axis=1) >= 6) & (np.abs(np.linalg.det(S3)) > 1e-12)
    S3[~ok] = np.eye(3)
    T = -np.linalg.solve(S3, S2.transpose(0, 2, 1))
    M = S1 + S2 @ T
    M = np.stack([M[:, 2] / 2, -M[:, 1], M[:, 0] / 2], axis=1)
    M[~np.all(np.isfinite(M), axis=(1, 2))] = np.eye(3)
    _, evecs = np.linalg.eig(M)
    evecs = np.real(evecs)
    cond = 4 * evecs[:, 0, :] * evecs[:, 2, :] - evecs[:, 1, :] ** 2
    pos = cond > 0
    ok &= pos.any(axis=1)
    k = np.argmax(pos, axis=1)
    a1 = evecs[np.arange(n), :, k]
    a2 = np.einsum("nij,nj->ni", T, a1)
    A, B, C = a1[:, 0], a1[:, 1], a1[:, 2]
    D, E, F = a2[:, 0], a2[:, 1], a2[:, 2]
    s2 = s * s
    out = np.column_stack([
        A / s2, B / s2, C / s2,
        -2 * A * mx / s2 - B * my / s2 + D / s,
        -2 * C * my / s2 - B * mx / s2 + E / s,
        (A * mx * mx + B * mx * my + C * my * my) / s2 - (D * mx + E * my) / s + F,
    ])
    return out, ok


def conic_centres(q: FloatArray) -> FloatArray:
    """(n, 2) centres of (n, 6) conics."""
    a, b, c, d, e = q[:, 0], q[:, 1], q[:, 2], q[:, 3], q[:, 4]
    det = 4 * a * c - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.column_stack([(b * e - 2 * c * d) / det, (b * d - 2 * a * e) / det])


def _conic_radius(q: FloatArray, centre: FloatArray, phi: FloatArray) -> FloatArray:
    """(n, k) distance from each centre to its conic along directions ``phi`` (n, k)."""
    a, b, c, d, e, f = (q[:, i : i + 1] for i in range(6))
    cx, cy = centre[:, 0:1], centre[:, 1:2]
    f0 = a * cx * cx + b * cx * cy + c * cy * cy + d * cx + e * cy + f
    co, si = np.cos(phi), np.sin(phi)
    quad = a * co * co + b * co * si + c * si * si
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(-f0 / quad)


def refine_marks(img: NDArray[np.float32], centres: FloatArray, semi_axes: FloatArray, angles_rad: FloatArray,
                 passes: int = 2) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Sub-pixel ellipse centres of dark marks, batched: (n, 2) centres and an ok flag each.

    Edge points: along rays from the current centre, the crossing of the mid grey level between
    the ray's own inner and outer levels (linear interpolation between samples), then a direct
    ellipse fit with outlier rejection; ``passes`` times, re-casting the rays from the new fit.
    A mark whose edge is not clean on most rays (hidden, merged, cut) is flagged not ok.
    """
    n = len(centres)
    c = centres.astype(np.float64).copy()
    ok = np.ones(n, dtype=bool)
    if n == 0:
        return c, ok
    mean_r = semi_axes.mean(axis=1)
    n_rays = int(np.clip(2 * np.pi * np.median(mean_r) / 1.0, 32, 200))
    phi1 = np.arange(n_rays) * (2 * np.pi / n_rays)
    phi = np.broadcast_to(phi1, (n, n_rays))
    co = np.cos(phi - angles_rad[:, None])
    si = np.sin(phi - angles_rad[:, None])
    rho = 1.0 / np.sqrt((co / semi_axes[:, 0:1]) ** 2 + (si / semi_axes[:, 1:2]) ** 2)
    n_s = 33
    t = np.linspace(-1.0, 1.0, n_s)
    cos_p, sin_p = np.cos(phi1), np.sin(phi1)
    rows_i = np.arange(n)[:, None]
    rays_i = np.arange(n_rays)[None, :]
    for _ in range(passes):
        half = np.maximum(0.45 * rho, 2.0)
        dist = np.maximum(rho[:, :, None] + half[:, :, None] * t, 0.5)  # (n, rays, samples)
        uu = c[:, 0, None, None] + dist * cos_p[None, :, None]
        vv = c[:, 1, None, None] + dist * sin_p[None, :, None]
        prof = _sample(img, uu, vv)
        q5 = n_s // 5
        inner = prof[:, :, :q5].mean(axis=2)
        outer = prof[:, :, -q5:].mean(axis=2)
        contrast = outer - inner
        thr = 0.5 * (inner + outer)
        above = prof >= thr[:, :, None]
        flips = above[:, :, 1:] & ~above[:, :, :-1]
        centre_idx = (n_s - 1) / 2
        cand = np.where(flips, np.abs(np.arange(n_s - 1) + 0.5 - centre_idx), np.inf)
        j = np.argmin(cand, axis=2)
        has = np.isfinite(np.take_along_axis(cand, j[:, :, None], axis=2)[:, :, 0])
        p0 = prof[rows_i, rays_i, j]
        p1 = prof[rows_i, rays_i, j + 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = (thr - p0) / (p1 - p0)
        d0 = dist[rows_i, rays_i, j]
        d1 = dist[rows_i, rays_i, j + 1]
        r_edge = d0 + frac * (d1 - d0)
        med_c = np.median(contrast, axis=1)
        good = has & np.isfinite(r_edge) & (contrast > 0.5 * med_c[:, None]) & (med_c[:, None] > 8)
        ok &= good.sum(axis=1) >= max(12, 0.6 * n_rays)
        r_edge = np.where(good, r_edge, rho)
        ex = c[:, 0:1] + r_edge * cos_p
        ey = c[:, 1:2] + r_edge * sin_p
        w = good.astype(np.float64)
        q, fit_ok = fit_ellipses_direct(ex, ey, w)
        ok &= fit_ok
        # reject outliers by radial residual and refit
        cn = conic_centres(q)
        rr = _conic_radius(q, cn, np.arctan2(ey - cn[:, 1:2], ex - cn[:, 0:1]))
        res = np.hypot(ex - cn[:, 0:1], ey - cn[:, 1:2]) - rr
        res = np.where(good & np.isfinite(res), res, np.nan)
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(np.where(ok[:, None], res, 0.0), axis=1)
            mad = np.nanmedian(np.abs(res - med[:, None]), axis=1) * 1.4826 + 1e-3
            keep = good & (np.abs(res - med[:, None]) < np.maximum(4 * mad, 0.05)[:, None])
        ok &= keep.sum(axis=1) >= max(12, 0.6 * n_rays)
        q, fit_ok = fit_ellipses_direct(ex, ey, keep.astype(np.float64))
        ok &= fit_ok
        cn = conic_centres(q)
        ok &= np.all(np.isfinite(cn), axis=1)
        ok &= np.hypot(*(np.nan_to_num(cn, nan=1e9) - c).T) < mean_r
        c = np.where(ok[:, None], cn, c)
        rho_new = _conic_radius(q, c, phi)
        good_rho = np.all(np.isfinite(rho_new), axis=1)
        ok &= good_rho
        rho = np.where(ok[:, None], rho_new, rho)
    return c, ok


# ---------------------------------------------------------------------------------------------
# perspective bias


def local_homographies(grid_xy: FloatArray, uv: FloatArray, neighbourhood: int = 2) -> FloatArray:
    """(N, 3, 3) homographies from plate (pitches, relative to mark i) to image (relative to uv[i]).

    Each is a DLT over the marks within ``neighbourhood`` grid steps of mark i (all marks if
    fewer than 9), batched: normalized coordinates, smallest eigenvector of ``AᵀA``.
    """
    d = np.max(np.abs(grid_xy[:, None, :] - grid_xy[None, :, :]), axis=2)  # (n, n)
    w = (d <= neighbourhood).astype(np.float64)
    few = w.sum(axis=1) < 9
    w[few] = 1.0
    return _weighted_local_h(grid_xy, uv, w)


def _weighted_local_h(grid_xy: FloatArray, uv: FloatArray, w: FloatArray) -> FloatArray:
    """Batched DLT: homography i fitted to all marks with weights ``w[i]``, in coordinates relative to mark i."""
    n = len(uv)
    X = grid_xy[None, :, :] - grid_xy[:, None, :]  # (n, n, 2) plate, relative
    U = uv[None, :, :] - uv[:, None, :]  # (n, n, 2) image, relative
    su = np.sqrt((w[:, :, None] * U**2).sum(axis=(1, 2)) / np.maximum(w.sum(axis=1), 1)) + 1e-12
    sx = np.sqrt((w[:, :, None] * X**2).sum(axis=(1, 2)) / np.maximum(w.sum(axis=1), 1)) + 1e-12
    Xn = X / sx[:, None, None]
    Un = U / su[:, None, None]
    x, y = Xn[..., 0], Xn[..., 1]
    u, v = Un[..., 0], Un[..., 1]
    z, o = np.zeros_like(x), np.ones_like(x)
    r1 = np.stack([x, y, o, z, z, z, -u * x, -u * y, -u], axis=2)
    r2 = np.stack([z, z, z, x, y, o, -v * x, -v * y, -v], axis=2)
    A = np.concatenate([r1, r2], axis=1) * np.concatenate([w, w], axis=1)[:, :, None]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", A, A))
    Hn = vecs[:, :, 0].reshape(n, 3, 3)
    Su = np.zeros((n, 3, 3))
    Su[:, 0, 0] = Su[:, 1, 1] = su
    Su[:, 2, 2] = 1
    Sx = np.zeros((n, 3, 3))
    Sx[:, 0, 0] = Sx[:, 1, 1] = 1 / sx
    Sx[:, 2, 2] = 1
    return np.asarray(Su @ Hn @ Sx, dtype=np.float64)


def _consistent(grid_xy: FloatArray, uv: FloatArray, neighbourhood: int = 2) -> NDArray[np.bool_]:
    """Marks whose position agrees with the homography of their grid neighbours (leave-one-out).

    The tolerance is 1.5% of the local pitch plus 0.15 px (far above the sub-pixel noise, far below
    the ~10% of a pitch that a half-hidden mark's centre moves), or four times the median
    residual when strong lens distortion makes the local homography itself that inexact. The
    worst offender is dropped and the test repeated.
    """
    n = len(uv)
    keep = np.ones(n, dtype=bool)
    d = np.max(np.abs(grid_xy[:, None, :] - grid_xy[None, :, :]), axis=2)
    for _ in range(8):
        w = ((d <= neighbourhood) & (d > 0) & keep[None, :]).astype(np.float64)
        few = w.sum(axis=1) < 6
        w[few] = ((d > 0) & keep[None, :])[few]
        H = _weighted_local_h(grid_xy, uv, w)
        pred = H[:, :2, 2] / H[:, 2:3, 2]  # image of the mark's own grid point, relative to its uv
        step_h = H @ np.array([1.0, 0.0, 1.0])
        step = step_h[:, :2] / step_h[:, 2:3] - pred
        resid_px = np.hypot(*pred.T)
        typical = float(np.median(resid_px[keep])) if keep.any() else 0.0
        resid = resid_px / np.maximum(0.015 * np.hypot(*step.T) + 0.15, 4.0 * typical)
        resid[~np.isfinite(resid)] = np.inf
        worst = int(np.argmax(np.where(keep, resid, -1.0)))
        if resid[worst] <= 1.0:
            break
        keep[worst] = False
    return keep


def perspective_bias(grid_xy: FloatArray, uv: FloatArray, radius_pitch: float, sigma_pitch: float = 1.0,
                     n_rim: int = 64) -> FloatArray:
    """(N, 2) bias of each mark (imaged-ellipse centre - image of its centre), no camera needed.

    ``grid_xy`` are the marks' plate coordinates in pitches, ``uv`` the current estimates of the
    images of their centres. Around each mark the plate-to-image mapping is modelled from the
    other marks, weighted by a Gaussian of their grid distance (``sigma_pitch``), as a homography
    plus a quadratic correction fitted to the homography's residuals, which follows lens
    distortion's curvature. The mark's rim is mapped through that model, an ellipse fitted to it
    (as the detector does to the real edge), and the bias is the ellipse's centre minus the mapped
    centre (Heikkilä 2000). bench/detection.py: at 45° tilt this leaves 0.006 px RMS on a
    distortion-free camera; a plain local homography left twice as much under strong distortion.
    With fewer than 12 marks the correction is left out (homography only).
    """
    d = np.max(np.abs(grid_xy[:, None, :] - grid_xy[None, :, :]), axis=2)
    w = np.exp(-0.5 * (d / sigma_pitch) ** 2)
    H = _weighted_local_h(grid_xy, uv, w)
    few = np.full(len(uv), len(uv) < 12)
    X = grid_xy[None, :, :] - grid_xy[:, None, :]  # (n, n, 2) plate, relative to mark i
    U = uv[None, :, :] - uv[:, None, :]  # (n, n, 2) image, relative to mark i
    P = np.einsum("nij,nmj->nmi", H, np.concatenate([X, np.ones(X.shape[:2] + (1,))], axis=2))
    res = U - P[..., :2] / P[..., 2:3]
    x, y = X[..., 0], X[..., 1]
    A = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=2) * w[:, :, None]
    AtA = np.einsum("nmi,nmj->nij", A, A) + 1e-9 * np.eye(6)
    coef = np.linalg.solve(AtA, np.einsum("nmi,nmk->nik", A, res * w[:, :, None]))  # (n, 6, 2)
    coef[few] = 0.0
    t = np.linspace(0.0, 2 * np.pi, n_rim, endpoint=False)
    bx, by = radius_pitch * np.cos(t), radius_pitch * np.sin(t)
    Pb = np.einsum("nij,kj->nki", H, np.stack([bx, by, np.ones_like(bx)], axis=1))
    rim = Pb[..., :2] / Pb[..., 2:3]
    rim = rim + np.einsum("kj,njc->nkc", np.stack([bx * bx, bx * by, by * by, bx, by, np.ones_like(bx)], axis=1),
                          coef)
    q, _ = fit_ellipses_direct(rim[..., 0], rim[..., 1], np.ones(rim.shape[:2]))
    centre = H[:, :2, 2] / H[:, 2:3, 2] + coef[:, 5, :]
    return np.asarray(conic_centres(q) - centre, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# the detector


def _attempt(grey: NDArray[np.uint8], img: NDArray[np.float32], binary: NDArray[np.uint8], target: CirclePlate,
             image_name: str) -> Detection | _Failure:
    cols, rows = target.cols, target.rows
    n_expected = cols * rows
    max_missing = max(2, n_expected // 10)
    frames = _frames(binary)
    if not frames:
        return _Failure(0, "no frame: no dark frame around a bright field with marks was found "
                        "(plate cropped, occluded frame, or too little contrast)")
    failure: _Failure | None = None
    for frame in frames[:3]:
        if len(frame.marks) > n_expected + max_missing:
            f = _Failure(1, f"mark count mismatch: {len(frame.marks)} marks inside the frame, the target "
                         f"has {cols}x{rows} = {n_expected}")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        found_k: tuple[int, FloatArray, NDArray[np.int64], NDArray[np.int64]] | None = None
        # The printed side faces the camera unless only the mirror image fits (mirrored views).
        for mirrored in (False, True):
            assigned = _assign(frame, cols, rows, mirrored)
            if assigned is None:
                f = _Failure(1, f"mark count mismatch: the {len(frame.marks)} marks inside the frame do not "
                             f"form the target's {cols}x{rows} grid")
                failure = failure if failure and failure.stage > f.stage else f
                continue
            H, idx, ids, _ = assigned
            unmatched = len(frame.marks) - len(idx)
            if len(idx) < n_expected - max_missing or unmatched > max_missing:
                f = _Failure(1, f"mark count mismatch: {len(idx)} of {n_expected} marks of the {cols}x{rows} "
                             f"grid found ({unmatched} other blobs inside the frame)")
                failure = failure if failure and failure.stage > f.stage else f
                continue
            k, why = _orientation(grey, H, cols, rows, _grid_xy(ids, cols), frame.marks[idx])
            if k >= 0 and cols != rows and k in (1, 3):
                k, why = -1, ("orientation unreadable: the triangle is in a corner that does not fit the "
                              f"plate's {cols}x{rows} shape")
            if k < 0:
                f = _Failure(2, why)
                failure = failure if failure and failure.stage > f.stage else f
                continue
            found_k = (k, H, idx, ids)
            break
        if found_k is None:
            continue
        k, H, idx, ids = found_k
        # re-express ids so that the triangle corner is the target's (-1, -1)
        gx, gy = ids % cols, ids // cols
        if k == 0:
            nx, ny = gx, gy
        elif k == 2:
            nx, ny = cols - 1 - gx, rows - 1 - gy
        elif k == 1:
            nx, ny = gy, cols - 1 - gx
        else:
            nx, ny = rows - 1 - gy, gx
        new_ids = (ny * cols + nx).astype(np.int64)
        # sub-pixel ellipses
        ells = [frame.ellipses[m] for m in idx]
        c0 = np.array([e[0] for e in ells], dtype=np.float64)
        axes = np.array([e[1] for e in ells], dtype=np.float64) / 2
        angs = np.deg2rad(np.array([e[2] for e in ells], dtype=np.float64))
        centres, ok = refine_marks(img, c0, axes, angs)
        uv_ell = centres[ok]
        new_ids = new_ids[ok]
        if len(new_ids) < n_expected - max_missing:
            f = _Failure(1, f"mark count mismatch: only {len(new_ids)} of {n_expected} marks have a clean edge "
                         "(occluded or blurred)")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        order = np.argsort(new_ids)
        new_ids, uv_ell = new_ids[order], uv_ell[order]
        grid = _grid_xy(new_ids, cols)
        radius_pitch = target.diameter_mm / 2 / target.pitch_mm
        # a mark that its neighbours do not predict is partly hidden or merged: leave it out
        keep = _consistent(grid, uv_ell)
        new_ids, uv_ell, grid = new_ids[keep], uv_ell[keep], grid[keep]
        if len(new_ids) < n_expected - max_missing:
            f = _Failure(1, f"mark count mismatch: only {len(new_ids)} of {n_expected} marks fit the plate "
                         "(occluded or damaged)")
            failure = failure if failure and failure.stage > f.stage else f
            continue
        uv = uv_ell.copy()
        for _ in range(2):
            uv = uv_ell - perspective_bias(grid, uv, radius_pitch)
        return Detection(image_name, True, ids=new_ids, uv=uv, uv_ellipse=uv_ell)
    assert failure is not None
    return failure


def detect_circle_plate(grey: NDArray[np.uint8], target: CirclePlate, image_name: str = "") -> Detection:
    """Marks of ``target`` in ``grey`` with plate-frame ids, bias-corrected centres, or a reason why not."""
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), EDGE_SMOOTH_SIGMA_PX)
    best: _Failure | None = None
    for binary in _binarizations(grey):
        r = _attempt(grey, img, binary, target, image_name)
        if isinstance(r, Detection):
            return r
        if best is None or r.stage > best.stage:
            best = r
    assert best is not None
    return Detection(image_name, False, reason=best.reason)
