"""The bundle problem of the splined stereographic model (``calibration.splined``): residuals, Jacobian, solve.

Unknowns, in the Jacobian's column order: the core ``fx, fy, cx, cy`` (px), the spline's control
values (all x corrections, then all y, row-major over the ``Nx x Ny`` grid; stereographic units),
every view's pose (left rotation increment ``w``, ``R <- exp(w) R``, then translation in metres)
and, with a board warp, the target's two warp heights (metres). Residuals are in pixels, each
point's weighted by its relative weight ``w``.

- **Solve** (``_Problem.solve``): Levenberg-Marquardt over the control values and every pose; the
  core stays at the start's (a B-spline reproduces constant and linear functions exactly, so the
  correction absorbs any change of the focal lengths or the centre; estimating both is a gauge
  freedom that LM walks along for ever), with an analytic sparse Jacobian and the normal equations
  solved densely (a few thousand unknowns).
- **Regularisation** (so that control points the data barely see do not fold the map): rows
  ``f sigma / PRIOR_PX (c - c0)`` pull every control value towards ``c0``, the spline that
  reproduces the start (fisheye4) lens over the whole grid (``initial_ctrl``); each weighs as one
  observation of the start's residual noise ``sigma`` at ``PRIOR_PX`` pixels off. A knot with many
  points follows them; one with a few follows the parametric lens's radial shape. (mrcal pulls the
  control values towards 0, i.e. towards the bare stereographic lens, with a weight that is a
  fixed share of the cost; on the fisheye set's sparse image corners that let the two halves'
  splines differ by up to 18 px.) A weak curvature term (second differences along both grid axes,
  ``REG_SHARE`` of the cost at ``TYPICAL_CURVATURE``) keeps the map smooth.
- **Gauge** (``_gauge``): rows pinning the correction and its curl at the axis (the camera-rotation gauge).

``splined_solver.calibrate_splined`` sets it up from the fisheye4 start and reads the result off it.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from calibration import splined
from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3
from calibration.intrinsics.results import F64, IntrinsicsError

REG_SHARE: Final = 1e-3
"""The curvature term's cost at typical values, as a share of the observations' cost at 1 px each."""
PRIOR_PX: Final = 3.0
"""A control value this many pixels off the start model's costs as one observation off by its noise: a
knot with many points follows them, one the data barely see follows the start (parametric) lens."""
TYPICAL_CURVATURE: Final = 0.05
"""A typical second difference of the control values (a fisheye's ~0.06 at the grid's edge)."""


GAUGE_WEIGHT: Final = 100.0
"""Weight (px per stereographic unit, per sqrt(observation)) of the gauge rows (``_gauge``)."""
REL_TOL: Final = 1e-8
"""Levenberg-Marquardt stops when a step lowers the cost by less than this fraction."""


class _Problem:
    """The bundle problem of the splined model: residuals and the sparse Jacobian."""

    def __init__(self, lay: splined.SplineLayout, X: F64, obs: F64, view: np.ndarray, n_views: int,
                 warp_basis: F64 | None = None) -> None:
        self.lay, self.X, self.obs, self.view, self.V = lay, X, obs, view, n_views
        self.nc = lay.n_ctrl
        self.n_intr = 4 + 2 * self.nc
        self.basis = warp_basis
        """(M, 2) the board-warp basis of each point (``views.warp_basis``), or None: a flat target."""
        self.nw = 0 if warp_basis is None else 2
        self.wp = np.zeros(self.nw)
        """The target's two warp heights (m), after the poses in the unknowns."""
        self.n = self.n_intr + 6 * n_views + self.nw
        self.D = _regulariser(lay)
        self.G = _gauge(lay)
        self.c0 = np.zeros(2 * self.nc)
        self.sigma_px = 1.0
        """The start's residual per coordinate (px): the prior's rows weigh as observations of this noise."""
        """The prior the control values are pulled towards (``initial_ctrl``: the start model)."""

    def reg_scales(self, n_obs: int, f: float) -> tuple[float, float]:
        """Weights (px per stereographic unit) of the prior and the curvature regularisation rows:
        a control value ``PRIOR_PX`` (times ``f``: pixels) off the prior costs as one observation
        off by 1 px; the curvature at a typical value costs ``REG_SHARE`` of ``n_obs`` residuals of 1 px."""
        a = f * self.sigma_px / PRIOR_PX
        b = np.sqrt(REG_SHARE * n_obs / (2 * self.D.shape[0])) / TYPICAL_CURVATURE
        return float(a), float(b)

    def initial_ctrl(self, core: F64, cam0: CameraModel) -> F64:
        """Control values that reproduce the start model ``cam0`` over the whole grid (sampled 4x
        per knot interval where ``cam0`` projects): the prior ``c0`` the regulariser pulls towards."""
        kx, ky = self.lay.knots()
        g = np.linspace(0.0, 1.0, 4 * (self.lay.nx - 1) + 1)
        gy = np.linspace(0.0, 1.0, 4 * (self.lay.ny - 1) + 1)
        uu, vv = np.meshgrid(kx[0] + g * (kx[-1] - kx[0]), ky[0] + gy * (ky[-1] - ky[0]))
        u = np.column_stack([uu.ravel(), vv.ravel()])
        r2 = np.sum(u * u, axis=1)
        u = u[r2 < 3.9]                                     # rays short of 90 deg off the axis
        xy = u / (1.0 - np.sum(u * u, axis=1) / 4.0)[:, None]
        q0 = cam0.project(np.column_stack([xy, np.ones(len(u))]))
        target = (q0 - core[2:4]) / core[:2] - u
        ok = np.all(np.isfinite(target), axis=1)
        idx, w, _ = self.lay.support(u[ok])
        rows = np.repeat(np.arange(ok.sum()), 16)
        A = sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(int(ok.sum()), self.nc))
        M = (A.T @ A + 1e-6 * sp.eye(self.nc) + 1e-3 * (self.D.T @ self.D)).tocsc()
        lu = sp.linalg.splu(M)
        c0 = np.concatenate([lu.solve(A.T @ target[ok, 0]), lu.solve(A.T @ target[ok, 1])])
        self.c0 = c0
        return c0.copy()

    def project(self, x: F64, R: F64, t: F64, wp: F64 | None = None, jac: bool = False
                ) -> tuple[F64, sp.csr_matrix | None]:
        """(M, 2) pixels and, with ``jac``, the (2M, n) Jacobian (intrinsics, 6 per view, then the
        warp's two heights ``wp``, default ``self.wp``)."""
        lay, X, view = self.lay, self.X, self.view
        wp = self.wp if wp is None else wp
        if self.nw:
            assert self.basis is not None
            X = X.copy()
            X[:, 2] += self.basis @ wp
        f, c = x[:2], x[2:4]
        ctrl = x[4:self.n_intr].reshape(2, self.nc)
        P = np.einsum("nij,nj->ni", R[view], X) + t[view]
        u, Ju = splined.stereographic(P)
        ok = np.all(np.isfinite(u), axis=1)
        uu = np.where(ok[:, None], u, 0.0)
        idx, w, dw = lay.support(uu)
        cx, cy = ctrl[0][idx], ctrl[1][idx]
        d = np.column_stack([np.sum(w * cx, axis=1), np.sum(w * cy, axis=1)])
        q = f * (uu + d) + c
        q[~ok] = np.nan
        if not jac:
            return q, None
        M = len(X)
        Jd = np.stack([np.einsum("nk,nka->na", cx, dw), np.einsum("nk,nka->na", cy, dw)], axis=1)
        A = f[None, :, None] * (np.eye(2)[None] + Jd)          # dq/du (M, 2, 2)
        dP = np.einsum("nab,nbc->nac", A, np.where(ok[:, None, None], Ju, 0.0))  # dq/dP (M, 2, 3)
        RX = P - t[view]
        # left increment R <- exp(w) R: dP/dw = -[R X]x
        skew = np.zeros((M, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -RX[:, 2], RX[:, 1], -RX[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = RX[:, 2], -RX[:, 1], RX[:, 0]
        dW = -np.einsum("nac,ncb->nab", dP, skew)
        rows_x, rows_y = 2 * np.arange(M), 2 * np.arange(M) + 1
        one = np.ones(M)
        ri, ci, vals = [], [], []

        def put(r: np.ndarray, cidx: np.ndarray, v: np.ndarray) -> None:
            ri.append(np.broadcast_to(r[:, None], v.shape).ravel())
            ci.append(np.broadcast_to(cidx, v.shape).ravel())
            vals.append(v.ravel())
        put(rows_x, np.array([0]), (uu[:, 0] + d[:, 0])[:, None])
        put(rows_y, np.array([1]), (uu[:, 1] + d[:, 1])[:, None])
        put(rows_x, np.array([2]), one[:, None])
        put(rows_y, np.array([3]), one[:, None])
        put(rows_x, 4 + idx, f[0] * w)
        put(rows_y, 4 + self.nc + idx, f[1] * w)
        pose = self.n_intr + 6 * view
        for a, rows in ((0, rows_x), (1, rows_y)):
            put(rows, pose[:, None] + np.arange(3)[None], dW[:, a, :])
            put(rows, pose[:, None] + 3 + np.arange(3)[None], dP[:, a, :])
        if self.nw:
            assert self.basis is not None
            dz = np.einsum("nab,nb->na", dP, R[view][:, :, 2])          # dq / d(target z)
            wcol = self.n_intr + 6 * self.V + np.arange(2)[None]
            for a, rows in ((0, rows_x), (1, rows_y)):
                put(rows, wcol, dz[:, a, None] * self.basis)
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(ri), np.concatenate(ci))), shape=(2 * M, self.n))
        return q, J

    def obs_residuals(self, x: F64, R: F64, t: F64, wp: F64 | None = None) -> F64:
        q, _ = self.project(x, R, t, wp=wp)
        return (q - self.obs).reshape(-1)

    def reg_rows(self, x: F64, n_obs: int, jac: bool = False) -> tuple[F64, sp.csr_matrix | None]:
        """Regularisation residuals (px) and their Jacobian over all unknowns."""
        a, b = self.reg_scales(n_obs, float(np.mean(x[:2])))
        ctrl = x[4:self.n_intr].reshape(2, self.nc)
        dev = ctrl - self.c0.reshape(2, self.nc)
        g = GAUGE_WEIGHT * np.sqrt(n_obs)
        r = np.concatenate([a * dev[0], a * dev[1], b * (self.D @ ctrl[0]), b * (self.D @ ctrl[1]),
                            g * (self.G @ x[4:self.n_intr])])
        if not jac:
            return r, None
        nc = self.nc
        Z = sp.csr_matrix((nc, nc))
        blocks = sp.vstack([sp.bmat([[a * sp.eye(nc), Z], [Z, a * sp.eye(nc)],
                                     [b * self.D, None], [None, b * self.D]]), g * self.G], format="csr")
        J = sp.hstack([sp.csr_matrix((len(r), 4)), blocks, sp.csr_matrix((len(r), 6 * self.V + self.nw))],
                      format="csr")
        return r, J

    def cost(self, x: F64, R: F64, t: F64, w: F64, wp: F64 | None = None) -> tuple[float, F64]:
        ro = self.obs_residuals(x, R, t, wp) * np.repeat(w, 2)
        rr, _ = self.reg_rows(x, int(2 * np.sum(w > 0)))
        r = np.concatenate([ro, rr])
        return (float(r @ r) if np.all(np.isfinite(r)) else float("inf")), r

    def normal(self, x: F64, R: F64, t: F64, w: F64) -> tuple[F64, F64, sp.csr_matrix, sp.csr_matrix]:
        q, Jo = self.project(x, R, t, jac=True)
        assert Jo is not None
        W = sp.diags(np.repeat(w, 2))
        Jo = W @ Jo
        ro = (q - self.obs).reshape(-1) * np.repeat(w, 2)
        rr, Jr = self.reg_rows(x, int(2 * np.sum(w > 0)), jac=True)
        assert Jr is not None
        J = sp.vstack([Jo, Jr], format="csr")
        r = np.concatenate([ro, rr])
        J = J[:, 4:]            # the core (fx, fy, cx, cy) is held (module docstring, step 3)
        Jo = Jo[:, 4:]
        H = (J.T @ J).toarray()
        g = J.T @ r
        return H, g, Jo, J

    def step(self, x: F64, R: F64, t: F64, dx: F64) -> tuple[F64, F64, F64, F64]:
        """Move by ``dx`` over every unknown (the Jacobian's columns; the core's step is 0 in the solve)."""
        x2 = x + dx[:self.n_intr]
        dv = dx[self.n_intr:self.n_intr + 6 * self.V].reshape(-1, 6)
        R2 = np.einsum("nij,njk->nik", exp_so3(dv[:, :3]), R)
        return x2, R2, t + dv[:, 3:], self.wp + dx[self.n_intr + 6 * self.V:]

    def solve(self, x: F64, R: F64, t: F64, w: F64, max_iter: int) -> tuple[F64, F64, F64, int]:
        cost, _ = self.cost(x, R, t, w)
        if not np.isfinite(cost):
            raise IntrinsicsError("the splined model's start puts target points behind the camera")
        lam = 1e-3
        it = 0
        for it in range(1, max_iter + 1):  # noqa: B007
            H, g, _, _ = self.normal(x, R, t, w)
            d = np.sqrt(np.maximum(np.diag(H), 1e-300))
            Hs = H / d[:, None] / d[None, :]
            improved = False
            while lam < 1e10:
                try:
                    cf = scipy.linalg.cho_factor(Hs + lam * np.eye(len(d)), check_finite=False)
                    dx = np.r_[np.zeros(4), -scipy.linalg.cho_solve(cf, g / d, check_finite=False) / d]
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                x2, R2, t2, wp2 = self.step(x, R, t, dx)
                c2, _ = self.cost(x2, R2, t2, w, wp2)
                if c2 < cost:
                    rel = (cost - c2) / cost
                    x, R, t, cost, self.wp = x2, R2, t2, c2, wp2
                    lam = max(lam / 10, 1e-9)
                    improved = True
                    break
                lam *= 10
            if not improved or rel < REL_TOL:
                break
        return x, R, t, it


def _gauge(lay: splined.SplineLayout) -> sp.csr_matrix:
    """(3, 2 Nx Ny) rows over the control values ``[dx, dy]``: the correction at the axis (x and y)
    and its curl there. A rotation of the camera frame moves every ``u`` by nearly a constant (a
    tilt) or a rotation field (a roll) that the spline reproduces; these rows pin that gauge (the
    principal point is ``cx, cy`` and the correction does not turn the image about it)."""
    idx, w, dw = lay.support(np.zeros((1, 2)))
    nc = lay.n_ctrl
    G = np.zeros((3, 2 * nc))
    G[0, idx[0]] = w[0]
    G[1, nc + idx[0]] = w[0]
    G[2, idx[0]] = dw[0, :, 1]            # d(dx)/dy - d(dy)/dx
    G[2, nc + idx[0]] = -dw[0, :, 0]
    return sp.csr_matrix(G)


def _regulariser(lay: splined.SplineLayout) -> sp.csr_matrix:
    """Second differences of the control grid along x and along y (rows), row-major control index."""
    nx, ny = lay.nx, lay.ny
    rows, cols, vals = [], [], []
    k = 0
    for j in range(ny):
        for i in range(1, nx - 1):
            for di, v in ((-1, 1.0), (0, -2.0), (1, 1.0)):
                rows.append(k)
                cols.append(j * nx + i + di)
                vals.append(v)
            k += 1
    for j in range(1, ny - 1):
        for i in range(nx):
            for dj, v in ((-1, 1.0), (0, -2.0), (1, 1.0)):
                rows.append(k)
                cols.append((j + dj) * nx + i)
                vals.append(v)
            k += 1
    return sp.csr_matrix((vals, (rows, cols)), shape=(k, nx * ny))


