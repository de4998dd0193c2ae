"""Sub-pixel ellipse centres of dark marks (ray edges + direct least-squares ellipses, batched; our own).

Shared by the circle plate and the circle grid detectors."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calibration.detect.sampling import sample_bilinear

FloatArray = NDArray[np.float64]

# ---------------------------------------------------------------------------------------------
# sub-pixel ellipse fit


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


def conic_radius(q: FloatArray, centre: FloatArray, phi: FloatArray) -> FloatArray:
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
    """Sub-pixel ellipse centres of dark marks, batched: (n, 2) centres and an ok flag each
    (``refine_marks_precise`` without the precision)."""
    c, ok, _ = refine_marks_precise(img, centres, semi_axes, angles_rad, passes)
    return c, ok


def refine_marks_precise(img: NDArray[np.float32], centres: FloatArray, semi_axes: FloatArray,
                         angles_rad: FloatArray, passes: int = 2
                         ) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """Sub-pixel ellipse centres of dark marks, batched: (n, 2) centres, an ok flag and a 1-sigma
    centre uncertainty (px, per axis) each.

    Edge points: along rays from the current centre, the crossing of the mid grey level between
    the ray's own inner and outer levels (linear interpolation between samples), then a direct
    ellipse fit with outlier rejection; ``passes`` times, re-casting the rays from the new fit.
    A mark whose edge is not clean on most rays (hidden, merged, cut) is flagged not ok.
    The uncertainty is the RMS radial residual of the kept edge points about the last fit times
    ``sqrt(2 / n_kept)`` (a centre from ``n`` points spread around the rim).
    """
    n = len(centres)
    c = centres.astype(np.float64).copy()
    ok = np.ones(n, dtype=bool)
    sigma = np.full(n, np.inf)
    if n == 0:
        return c, ok, sigma
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
        prof = sample_bilinear(img, uu, vv)
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
        rr = conic_radius(q, cn, np.arctan2(ey - cn[:, 1:2], ex - cn[:, 0:1]))
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
        rho_new = conic_radius(q, c, phi)
        good_rho = np.all(np.isfinite(rho_new), axis=1)
        ok &= good_rho
        rho = np.where(ok[:, None], rho_new, rho)
        rr = conic_radius(q, cn, np.arctan2(ey - cn[:, 1:2], ex - cn[:, 0:1]))
        res_k = np.where(keep, np.hypot(ex - cn[:, 0:1], ey - cn[:, 1:2]) - rr, 0.0)
        n_k = np.maximum(keep.sum(axis=1), 1)
        with np.errstate(invalid="ignore"):
            sigma = np.sqrt(np.nansum(res_k**2, axis=1) / n_k) * np.sqrt(2.0 / n_k)
    sigma = np.where(ok & np.isfinite(sigma), sigma, np.inf)
    return c, ok, sigma
