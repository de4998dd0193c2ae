"""Projection uncertainty: coverage grid, covariance propagated to pixels, jackknife, comparing cameras."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from calibration import splined
from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3
from calibration.intrinsics.model import (
    NormalEquations,
    information_scale,
    intrinsic_steps,
    intrinsics_vector,
    project_normalized,
)
from calibration.intrinsics.results import (
    F64,
    IntrinsicsResult,
    fin,
)

# --------------------------------------------------------------------------------------------
# uncertainty


def cell_grid(size: tuple[int, int], nx: int = 16) -> tuple[F64, int, int]:
    w, h = size
    ny = max(4, int(round(nx * h / w)))
    us = (np.arange(nx) + 0.5) * w / nx - 0.5
    vs = (np.arange(ny) + 0.5) * h / ny - 0.5
    uu, vv = np.meshgrid(us, vs)
    return np.column_stack([uu.ravel(), vv.ravel()]), nx, ny


def _cells_of(size: tuple[int, int], uv: F64, nx: int) -> tuple[NDArray[np.int64], int, int]:
    """The row-major index of the image cell (of :func:`cell_grid`) each point ``uv`` (px) lies in."""
    w, h = size
    _, nx, ny = cell_grid(size, nx)
    ix = np.clip((uv[:, 0] + 0.5) * nx / w, 0, nx - 1).astype(np.int64)
    iy = np.clip((uv[:, 1] + 0.5) * ny / h, 0, ny - 1).astype(np.int64)
    return iy * nx + ix, nx, ny


def coverage_counts(size: tuple[int, int], uv: F64, nx: int = 16) -> NDArray[np.int64]:
    """(ny, nx) number of observed points in each image cell."""
    cell, nx, ny = _cells_of(size, np.asarray(uv, dtype=np.float64).reshape(-1, 2), nx)
    return np.bincount(cell, minlength=nx * ny).astype(np.int64).reshape(ny, nx)


def cell_point_means(size: tuple[int, int], uv: F64, nx: int = 16) -> F64:
    """(K, 2) mean pixel position of the observed points ``uv`` in each image cell that holds any,
    cells in row-major order (the order of ``coverage_counts(...) > 0``)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not len(uv):
        return np.zeros((0, 2))
    cell, nx, ny = _cells_of(size, uv, nx)
    n = np.bincount(cell, minlength=nx * ny).astype(np.float64)
    su = np.bincount(cell, weights=uv[:, 0], minlength=nx * ny)
    sv = np.bincount(cell, weights=uv[:, 1], minlength=nx * ny)
    k = n > 0
    return np.column_stack([su[k] / n[k], sv[k] / n[k]])


def projection_jacobians(camera: CameraModel, pts_px: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """For the rays through ``pts_px``: (2N, n_intr) d(pixel)/d(intrinsics), (2N, 3)
    d(pixel)/d(camera rotation) and a validity mask (N,)."""
    rays = camera.unproject(pts_px)
    xy = rays[:, :2]
    c = intrinsics_vector(camera)
    valid = np.all(np.isfinite(xy), axis=1)
    xy = np.where(valid[:, None], xy, 0.0)
    if camera.model == "splined":
        Jc = _splined_jacobian(camera, xy)
    else:
        hs = intrinsic_steps(c)
        Jc = np.empty((2 * len(xy), len(c)))
        for i in range(len(c)):
            e = np.zeros_like(c)
            e[i] = hs[i]
            Jc[:, i] = ((project_normalized(camera.model, c + e, xy)
                         - project_normalized(camera.model, c - e, xy)) / (2 * hs[i])).reshape(-1)
    Jw = np.empty((2 * len(xy), 3))
    P = np.column_stack([xy, np.ones(len(xy))])
    h = 1e-7
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        Pp = P @ exp_so3(w[None])[0].T
        Pm = P @ exp_so3(-w[None])[0].T
        Jw[:, k] = ((project_normalized(camera.model, c, Pp[:, :2] / Pp[:, 2:])
                     - project_normalized(camera.model, c, Pm[:, :2] / Pm[:, 2:])) / (2 * h)).reshape(-1)
    bad = ~np.all(np.isfinite(Jc), axis=1) | ~np.all(np.isfinite(Jw), axis=1)
    valid &= ~bad.reshape(-1, 2).any(axis=1)
    return np.nan_to_num(Jc), np.nan_to_num(Jw), valid


def _splined_jacobian(camera: CameraModel, xy: F64) -> F64:
    """(2N, n_intr) d(pixel)/d(intrinsics) of the splined model at the pinhole points ``xy``,
    analytic (the projection is linear in the control values): ``(u + delta)`` for fx / fy, 1 for
    cx / cy, 0 for the grid's layout, ``f`` times the B-spline weights for the control values."""
    lay, ctrl = splined.parse(camera.dist)
    u, _ = splined.stereographic(np.column_stack([xy, np.ones(len(xy))]))
    d, _ = splined.correction(lay, ctrl, u)
    idx, w, _ = lay.support(np.nan_to_num(u))
    n = len(xy)
    J = np.zeros((2 * n, 4 + splined.HEADER + 2 * lay.n_ctrl))
    rows = np.arange(n)
    J[2 * rows, 0] = u[:, 0] + d[:, 0]
    J[2 * rows + 1, 1] = u[:, 1] + d[:, 1]
    J[2 * rows, 2] = 1.0
    J[2 * rows + 1, 3] = 1.0
    base = 4 + splined.HEADER
    np.add.at(J, (np.repeat(2 * rows, 16), base + idx.ravel()), camera.fx * w.ravel())
    np.add.at(J, (np.repeat(2 * rows + 1, 16), base + lay.n_ctrl + idx.ravel()), camera.fy * w.ravel())
    return J


def projection_uncertainty(camera: CameraModel, cov: F64, pts_px: F64, fit_mask: NDArray[np.bool_]
                           ) -> F64:
    """1-sigma projection uncertainty (px, RMS length of the 2D error) at each of ``pts_px``,
    after compensating the rotation that best explains the change over ``fit_mask`` points."""
    Jc, Jw, valid = projection_jacobians(camera, pts_px)
    m = np.repeat(fit_mask & valid, 2)
    A = Jw[m]
    if A.shape[0] >= 6:
        G = np.linalg.pinv(A) @ Jc[m]            # best rotation per unit intrinsics change
        M = Jc - Jw @ G
    else:
        M = Jc
    Mi = M.reshape(len(pts_px), 2, -1)
    var = np.einsum("nai,ij,naj->n", Mi, cov, Mi)
    out = np.sqrt(np.maximum(var, 0.0))
    out[~valid] = np.nan
    return out


def named_points(size: tuple[int, int]) -> dict[str, tuple[float, float]]:
    w, h = size[0] - 1.0, size[1] - 1.0
    return {"centre": (w / 2, h / 2), "top_left": (0.0, 0.0), "top_right": (w, 0.0),
            "bottom_left": (0.0, h), "bottom_right": (w, h), "top": (w / 2, 0.0),
            "bottom": (w / 2, h), "left": (0.0, h / 2), "right": (w, h / 2)}


def uncertainty_summary(camera: CameraModel, cov: F64, coverage: NDArray[np.int64],
                        points_px: F64 | None = None) -> tuple[dict[str, Any], F64]:
    """The ``uncertainty`` block of ``cam.json`` and the per-cell map (at the cells' centres).

    With the observed points ``points_px`` (px) the covered region's RMS (``projection_rms_px``)
    is taken at the mean of the points in each covered cell, not at its centre: a cell the data
    only touch has its centre outside them, and there a flexible model's linearised uncertainty
    extrapolates (the rational model on 6 views reported 38.5 px in one such cell, 0.17-0.20 px in
    the others, for an actual error of 0.035 px)."""
    grid, nx, ny = cell_grid(camera.size, coverage.shape[1])
    covered = coverage.reshape(-1) > 0
    named = named_points(camera.size)
    pts = np.vstack([grid, np.array(list(named.values()))])
    fit = np.concatenate([covered, np.zeros(len(named), dtype=bool)])
    s = projection_uncertainty(camera, cov, pts, fit)
    s_grid, s_named = s[: len(grid)], dict(zip(named, s[len(grid):], strict=True))
    s_whole = projection_uncertainty(camera, cov, grid, np.ones(len(grid), dtype=bool))
    s_cov = s_grid[covered]
    if points_px is not None and len(points_px):
        at = cell_point_means(camera.size, points_px, coverage.shape[1])
        s_cov = projection_uncertainty(camera, cov, at, np.ones(len(at), dtype=bool))

    def rms(a: F64) -> float:
        a = a[np.isfinite(a)]
        return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")

    summary = {
        "projection_rms_px": fin(rms(s_cov)),
        "projection_rms_whole_image_px": fin(rms(s_whole)),
        "projection_max_px": fin(float(np.nanmax(s_grid)) if np.any(np.isfinite(s_grid)) else float("nan")),
        "centre_px": fin(float(s_named["centre"])),
        "corners_px": {k: fin(float(s_named[k])) for k in ("top_left", "top_right", "bottom_left",
                                                             "bottom_right")},
        "edges_px": {k: fin(float(s_named[k])) for k in ("top", "bottom", "left", "right")},
        "covered_fraction": float(covered.mean()),
        "method": "intrinsics covariance (marginalised over poses) propagated through projection of "
                  "rays through a pixel grid, best camera rotation compensated over the covered cells; "
                  "1-sigma RMS length of the pixel error" + ("; the covered region's RMS at the mean of the "
                                                             "points in each covered cell" if points_px is not None
                                                             else ""),
    }
    return summary, s_grid.reshape(ny, nx)


def jackknife_projection_rms(camera: CameraModel, nrm: NormalEquations, pts: F64, groups: int) -> float:
    """Grouped delete-a-group jackknife over views (view ``k`` in group ``k mod groups``), linearised:
    the RMS over ``pts`` of the jackknife standard deviation of each point's projection (best
    rotation compensated).

    Each replicate is one Gauss-Newton step from the full optimum with the group's terms removed
    from the normal equations (the influence function): with ``S_v`` a view's share of the Schur
    complement and ``h_v`` its share of the reduced gradient (which sums to ~0 at the optimum),
    the replicate's intrinsics move by ``(S - S_g)^-1 h_g``. Exact for a linear model; for ours it
    agrees with re-solving each replicate to first order, at the cost of one small solve instead
    of a bundle adjustment per replicate (the re-solves made intrinsics 20-90x slower than OpenCV).
    Done in pixel space, not parameter space, because the rational model's coefficients wander
    along a flat valley that projection does not see."""
    if nrm.Av is None or nrm.gcv is None:
        raise ValueError("the jackknife needs the per-view normal-equation blocks (normal_equations_at)")
    V = nrm.D.shape[0]
    G = min(V, groups)
    Dinv = np.linalg.inv(nrm.D)
    BDinv = nrm.B @ Dinv                                            # (V, nc, 6)
    Sv = nrm.Av - np.einsum("vij,vkj->vik", BDinv, nrm.B)           # (V, nc, nc)
    hv = nrm.gcv - np.einsum("vij,vj->vi", BDinv, nrm.gv)           # (V, nc)
    S = Sv.sum(axis=0)
    gid = np.arange(V) % G
    Jc, Jw, valid = projection_jacobians(camera, pts)
    m = np.repeat(valid, 2)
    M = Jc
    if Jw[m].shape[0] >= 6:
        M = Jc - Jw @ (np.linalg.pinv(Jw[m]) @ Jc[m])
    dq = np.empty((G, len(pts), 2))
    for g in range(G):
        Sr = S - Sv[gid == g].sum(axis=0)
        hg = hv[gid == g].sum(axis=0)
        sc = information_scale(Sr)
        dc = np.linalg.lstsq(Sr / sc[:, None] / sc[None, :], hg / sc, rcond=1e-14)[0] / sc
        dq[g] = (M @ dc[: M.shape[1]]).reshape(-1, 2)   # the lens's part (a board warp follows it)
    dq = dq[:, valid]
    if dq.shape[1] == 0:
        return float("nan")
    dev = dq - dq.mean(axis=0)
    var = (G - 1) / G * np.sum(dev * dev, axis=(0, 2))
    return float(np.sqrt(np.mean(var)))


# --------------------------------------------------------------------------------------------
# comparing cameras


ROUND_TRIP_PX = 0.01
"""``projection_difference`` leaves out pixels whose unprojected ray re-projects farther than this."""


def projection_difference(camera: CameraModel, reference: CameraModel, pts_px: ArrayLike | None = None,
                          fit_rotation: bool = True, nx: int = 32) -> dict[str, Any]:
    """How far ``camera`` projects the rays of ``reference``'s pixels from those pixels.

    For each pixel ``q`` (default: a grid over the whole image) the reference's ray is projected
    with ``camera`` after the rotation of the camera frame that minimises the total squared
    difference (``fit_rotation``). Returns RMS and max length (px), the rotation, the per-point
    differences and how many pixels were left out (the reference cannot unproject them: its
    model folds over there).
    """
    if pts_px is None:
        pts, _, _ = cell_grid(reference.size, nx)
    else:
        pts = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    rays = reference.unproject(pts)
    ok = np.all(np.isfinite(rays), axis=1)
    # A pixel whose ray does not project back onto it lies where the reference's polynomial folds
    # over (a wide lens under opencv5): the iterative undistortion returned a wrong ray there, and
    # two nearly equal cameras differed by 200 px on the GoPro set (issue 26). Such pixels are left out.
    back = np.full(len(pts), np.inf)
    back[ok] = np.linalg.norm(reference.project(rays[ok]) - pts[ok], axis=1)
    ok &= back < ROUND_TRIP_PX
    rays, pts = rays[ok], pts[ok]
    c = intrinsics_vector(camera)

    def diff(w: F64) -> F64:
        P = rays @ exp_so3(w[None])[0].T
        q = project_normalized(camera.model, c, P[:, :2] / P[:, 2:])
        d = q - pts
        return np.nan_to_num(d, nan=1e6).reshape(-1)

    w = np.zeros(3)
    if fit_rotation:
        w = least_squares(diff, w, method="lm", x_scale=1e-3).x
    d = diff(w).reshape(-1, 2)
    mag = np.linalg.norm(d, axis=1)
    return {"rms_px": float(np.sqrt(np.mean(mag**2))), "max_px": float(mag.max()),
            "rotation_deg": float(np.degrees(np.linalg.norm(w))), "diff_px": d, "points_px": pts,
            "points_left_out": int(np.sum(~ok))}


def covered_points(result: IntrinsicsResult) -> F64:
    """Centres of the image cells the calibration data covered (for ``projection_difference``)."""
    grid, _, _ = cell_grid(result.camera.size, result.coverage.shape[1])
    return grid[result.coverage.reshape(-1) > 0]


def covered_point_means(result: IntrinsicsResult) -> F64:
    """Mean position (px) of the calibration's points in each covered image cell: where
    ``uncertainty["projection_rms_px"]`` is evaluated (compare an actual error there)."""
    uv = [v.uv for v in result.views if v.used and len(v.uv)]
    return cell_point_means(result.camera.size, np.vstack(uv) if uv else np.zeros((0, 2)),
                            result.coverage.shape[1])
