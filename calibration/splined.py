"""The splined stereographic lens model (mrcal's ``LENSMODEL_SPLINED_STEREOGRAPHIC``, order 3).

A ray ``p = (x, y, z)`` in the camera frame (metres; x right, y down, z forward) goes to its
stereographic projection ``u = 2 (x, y) / (|p| + z)`` (unitless; ``|u| = 2 tan(theta / 2)`` with
``theta`` the ray's angle to the optical axis), a smooth 2-D correction ``delta(u)`` is added and
the result goes through the pinhole core: ``pixel = (fx (u + delta)_x + cx, fy (u + delta)_y + cy)``.

``delta`` is a tensor-product uniform cubic B-spline over the stereographic plane: ``Nx x Ny``
control values per axis on a square knot grid centred on the axis, spacing
``h = 2 u_edge / (Nx - 3)`` with ``u_edge = 2 tan(fov_x / 4)`` (the grid's interior spans the
horizontal field ``fov_x_deg``; one more knot interval on each side carries the cubic's support,
as mrcal lays it out). Outside the interior the edge segments' polynomials continue.

In a :class:`~calibration.camera_model.CameraModel` of model ``"splined"`` the coefficients are
``dist = [Nx, Ny, fov_x_deg, dx (Ny*Nx, row-major), dy (Ny*Nx)]``: the grid's layout first (fixed by
the calibration, never estimated), then the control values (unitless, stereographic-plane units;
times ``fx`` is pixels). The "distorted normalized" point of this model is ``u + delta(u)`` and the
ideal normalized point is the pinhole ``(x/z, y/z)`` (so rays are within 90 deg of the axis, as for
``fisheye4``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

HEADER = 3
"""Entries of ``dist`` before the control values: Nx, Ny, fov_x_deg."""


class SplineLayout:
    """The knot grid of a splined model: ``nx x ny`` control points, spacing ``h`` (stereographic units)."""

    def __init__(self, nx: int, ny: int, fov_x_deg: float) -> None:
        if nx < 4 or ny < 4:
            raise ValueError(f"a cubic spline needs at least 4 x 4 control points, got {nx} x {ny}")
        if not 0.0 < fov_x_deg < 360.0:
            raise ValueError(f"fov_x_deg must be in (0, 360), got {fov_x_deg}")
        self.nx, self.ny, self.fov_x_deg = int(nx), int(ny), float(fov_x_deg)
        self.u_edge = 2.0 * np.tan(np.radians(fov_x_deg) / 4.0)
        self.h = 2.0 * self.u_edge / (self.nx - 3)

    @property
    def n_ctrl(self) -> int:
        return self.nx * self.ny

    def header(self) -> F64:
        return np.array([self.nx, self.ny, self.fov_x_deg], dtype=np.float64)

    def knots(self) -> tuple[F64, F64]:
        """Positions of the control points along x and y (stereographic units)."""
        return ((np.arange(self.nx) - (self.nx - 1) / 2.0) * self.h,
                (np.arange(self.ny) - (self.ny - 1) / 2.0) * self.h)

    def support(self, u: F64) -> tuple[I64, F64, F64]:
        """For each point ``u`` (N, 2): the 16 control indices (N, 16) its value depends on, their
        weights (N, 16) and the weights' derivatives d/du (N, 16, 2)."""
        ix, tx = self._segment(u[:, 0], self.nx)
        iy, ty = self._segment(u[:, 1], self.ny)
        bx, dbx = _basis(tx)
        by, dby = _basis(ty)
        idx = ((iy[:, None, None] + np.arange(4)[None, :, None]) * self.nx
               + ix[:, None, None] + np.arange(4)[None, None, :]).reshape(-1, 16)
        w = (by[:, :, None] * bx[:, None, :]).reshape(-1, 16)
        dw = np.stack([(by[:, :, None] * dbx[:, None, :]).reshape(-1, 16),
                       (dby[:, :, None] * bx[:, None, :]).reshape(-1, 16)], axis=2) / self.h
        return idx, w, dw

    def _segment(self, s: F64, n: int) -> tuple[I64, F64]:
        """First of the 4 control points of each coordinate's segment and its local parameter
        (the edge segments continue outside the grid)."""
        g = s / self.h + (n - 1) / 2.0          # position in control-point units
        i = np.clip(np.floor(np.nan_to_num(g)), 1, n - 3).astype(np.int64)
        return i - 1, g - i


def _basis(t: F64) -> tuple[F64, F64]:
    """Uniform cubic B-spline weights (N, 4) at local parameter ``t`` and their d/dt."""
    t2, t3 = t * t, t * t * t
    b = np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=1) / 6.0
    db = np.stack([-3 * (1 - t) ** 2, 9 * t2 - 12 * t, -9 * t2 + 6 * t + 3, 3 * t2], axis=1) / 6.0
    return b, db


def parse(dist: F64) -> tuple[SplineLayout, F64]:
    """The layout and the (2, Ny*Nx) control values of a splined model's ``dist`` vector."""
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    if d.size < HEADER:
        raise ValueError("a splined model's dist starts with Nx, Ny, fov_x_deg")
    lay = SplineLayout(int(round(d[0])), int(round(d[1])), float(d[2]))
    if d.size != HEADER + 2 * lay.n_ctrl:
        raise ValueError(f"a splined {lay.nx}x{lay.ny} model needs {HEADER + 2 * lay.n_ctrl} dist entries "
                         f"(Nx, Ny, fov_x_deg and 2 Nx Ny control values), got {d.size}")
    return lay, d[HEADER:].reshape(2, lay.n_ctrl)


def n_dist(nx: int, ny: int) -> int:
    return HEADER + 2 * nx * ny


def stereographic(P: F64) -> tuple[F64, F64]:
    """Stereographic projection ``u`` (N, 2) of camera-frame points ``P`` (N, 3) and du/dP (N, 2, 3)."""
    n = np.linalg.norm(P, axis=1)
    s = n + P[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 2.0 * P[:, :2] / s[:, None]
        # d(2 p_a / s)/dP = 2 e_a / s - 2 p_a / s^2 (P / n + e_z)
        ds = P / n[:, None]
        ds[:, 2] += 1.0
        J = -u[:, :, None] * ds[:, None, :] / s[:, None, None]
        J[:, 0, 0] += 2.0 / s
        J[:, 1, 1] += 2.0 / s
    bad = ~(s > 1e-12 * np.maximum(n, 1e-300))
    u[bad] = np.nan
    return u, J


def correction(lay: SplineLayout, ctrl: F64, u: F64) -> tuple[F64, F64]:
    """``delta(u)`` (N, 2) and its Jacobian d(delta)/du (N, 2, 2)."""
    ok = np.all(np.isfinite(u), axis=1)
    uu = np.where(ok[:, None], u, 0.0)
    idx, w, dw = lay.support(uu)
    cx, cy = ctrl[0][idx], ctrl[1][idx]
    d = np.column_stack([np.sum(w * cx, axis=1), np.sum(w * cy, axis=1)])
    J = np.stack([np.einsum("nk,nka->na", cx, dw), np.einsum("nk,nka->na", cy, dw)], axis=1)
    d[~ok] = np.nan
    return d, J


def distort(dist: F64, xy: F64) -> F64:
    """Pinhole normalized points ``(x/z, y/z)`` (N, 2) to this model's distorted normalized points
    ``u + delta(u)``."""
    lay, ctrl = parse(dist)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    u, _ = stereographic(np.column_stack([p, np.ones(len(p))]))
    d, _ = correction(lay, ctrl, u)
    return u + d


def undistort(dist: F64, q: F64, iterations: int = 30) -> F64:
    """Distorted normalized points ``u + delta(u)`` to pinhole normalized ``(x/z, y/z)``: Newton's
    method on ``u`` (2x2 Jacobian ``I + d delta/du``) to 1e-12, then the inverse stereographic map.
    NaN where Newton does not converge, the map folds (Jacobian determinant <= 0) or the ray is at
    or beyond 90 deg (``|u| >= 2``)."""
    lay, ctrl = parse(dist)
    q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
    u = q.copy()
    d, J = correction(lay, ctrl, u)
    u = q - np.nan_to_num(d)             # one fixed-point step: a good start for a small correction
    for _ in range(iterations):
        d, J = correction(lay, ctrl, u)
        f = u + d - q
        a, b, c, e = 1.0 + J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], 1.0 + J[:, 1, 1]
        det = a * e - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.column_stack([(e * f[:, 0] - b * f[:, 1]) / det, (-c * f[:, 0] + a * f[:, 1]) / det])
        u = u - step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-12:
            break
    d, J = correction(lay, ctrl, u)
    det = (1.0 + J[:, 0, 0]) * (1.0 + J[:, 1, 1]) - J[:, 0, 1] * J[:, 1, 0]
    r2 = np.sum(u * u, axis=1)
    bad = ~np.all(np.isfinite(u), axis=1) | (np.linalg.norm(u + d - q, axis=1) > 1e-9) | (det <= 0) | (r2 >= 4.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = u / (1.0 - r2 / 4.0)[:, None]
    xy[bad] = np.nan
    return xy


def layout_for_field(theta_x_max: float, u_y_max: float, nx: int) -> SplineLayout:
    """A layout of ``nx`` columns whose interior covers the horizontal half-angle ``theta_x_max``
    (rad) and whose rows cover ``|u_y| <= u_y_max`` (stereographic units), spacing equal in x and y."""
    fov = float(np.degrees(2.0 * theta_x_max))
    lay = SplineLayout(nx, 4, fov)
    ny = max(4, int(np.ceil(2.0 * u_y_max / lay.h)) + 3)
    return SplineLayout(nx, ny, fov)
