"""The vectorised projection model and our Levenberg-Marquardt bundle solver (Schur complement)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack

from calibration.camera_model import CameraModel, ModelName, distort_normalized
from calibration.intrinsics import kernels, schur_kernels
from calibration.intrinsics.results import (
    F64,
    IntrinsicsError,
)

# --------------------------------------------------------------------------------------------
# the vectorised model


def param_names(model: str) -> list[str]:
    names = {"opencv5": ["k1", "k2", "p1", "p2", "k3"],
             "opencv8": ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"],
             "division": ["kappa"], "fisheye4": ["k1", "k2", "k3", "k4"]}[model]
    return ["fx", "fy", "cx", "cy", *names]


def intrinsics_vector(camera: CameraModel) -> F64:
    return np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.dist])


def camera_from_vector(model: str, size: tuple[int, int], c: ArrayLike) -> CameraModel:
    c = np.asarray(c, dtype=np.float64)
    K = np.array([[c[0], 0.0, c[2]], [0.0, c[1], c[3]], [0.0, 0.0, 1.0]])
    return CameraModel(cast(ModelName, model), size[0], size[1], K, c[4:].copy())


def project_normalized(model: str, c: F64, xy: F64) -> F64:
    d = distort_normalized(model, c[4:], xy)
    return np.column_stack([c[0] * d[:, 0] + c[2], c[1] * d[:, 1] + c[3]])


@dataclass
class BundleProblem:
    """Observations sorted by view: rows ``starts[v]:starts[v+1]`` belong to view ``v``."""

    model: str
    size: tuple[int, int]
    X: F64          # (M, 3) target points, metres
    obs: F64        # (M, 2) observed pixels (bias-corrected for circle marks)
    view: NDArray[np.int64]
    starts: NDArray[np.int64]
    w: F64 | None = None
    """(M,) relative weight of each point (``calibration.observations.point_weights``), or None."""
    prior_w: F64 | None = None
    """Regularisation (``regularisation``): per-parameter weight (px per unit of the parameter, over the
    whole parameter vector, 0 where none), or None for an unregularised solve."""
    prior_at: F64 | None = None
    """The values the regularisation pulls the parameters toward (same length as ``prior_w``)."""

    @property
    def n_views(self) -> int:
        return len(self.starts) - 1

    @property
    def model_id(self) -> int:
        return kernels.MODEL_IDS[self.model]

    def weights(self) -> F64:
        return np.ones(len(self.X)) if self.w is None else self.w

    def project(self, c: F64, R: F64, t: F64) -> F64:
        """(M, 2) projected pixels (NaN for points that cannot be projected)."""
        r = kernels.residuals(self.model_id, np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(R),
                              np.ascontiguousarray(t), self.X, np.zeros_like(self.obs), np.ones(len(self.X)), self.view)
        return r.reshape(-1, 2)

    def prior_cost(self, c: F64) -> float:
        """The regularisation's share of the cost (px^2): ``sum (prior_w (c - prior_at))^2``."""
        if self.prior_w is None or self.prior_at is None:
            return 0.0
        e = self.prior_w * (np.asarray(c, dtype=np.float64)[: len(self.prior_w)] - self.prior_at)
        return float(np.sum(e * e))

    def residuals(self, c: F64, R: F64, t: F64) -> F64:
        """Weighted pixel residuals (the solver's cost): ``w_i (projected - observed)``, flattened."""
        return kernels.residuals(self.model_id, np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(R),
                                 np.ascontiguousarray(t), self.X, self.obs, self.weights(), self.view)


REG_SHARE = 0.0025
"""mrcal's rule (``regularisation``): each group of regularisation terms costs this share of the data's
expected chi^2 when its parameters sit at their "normal" values."""

REG_NORMAL_PIXEL_ERROR_PX = 1.0
REG_NORMAL_DISTORTION = 2.0
REG_NORMAL_CENTRE_OFFSET_PX = 500.0
REG_RATIONAL_FACTOR = 5.0
"""The rational model's denominator coefficients (opencv8's k4, k5, k6) are pulled this much harder."""

REGULARISABLE = ("opencv5", "opencv8")


def regularisation(model: str, size: tuple[int, int], n_measurements: int) -> tuple[F64, F64]:
    """Per-parameter weights (px per unit) and targets of a regularised solve, by mrcal's rule (mrcal
    2.2's ``optimizer_callback``, measured; ``docs/conventions.md``, camera models): a penalty
    ``sum (w_i (c_i - c0_i))^2`` added to the cost, with

    - every distortion coefficient pulled toward 0 with ``w_d^2 = N e^2 s / (n_d d^2)`` (``N`` the count of
      measurements, 2 per kept point; ``e`` = 1 px the normal pixel error, ``s`` = 0.25 %, ``n_d`` the
      count of distortion terms, ``d`` = 2 their normal size); the rational denominator's k4-k6 with 5 w_d
      (a rational model whose numerator and denominator both grow is ~0/0 with wild derivatives);
    - the principal point pulled toward the image centre ``((W - 1) / 2, (H - 1) / 2)`` with
      ``w_c^2 = N e^2 s / (2 o^2)``, ``o`` = 500 px.

    So each group costs ~0.25 % of the data's chi^2 (at 1 px per coordinate) at its normal value: the
    fit's well-determined parameters hardly move (a 0.1 change of k1 costs ~1e-5 of the data's chi^2),
    while the directions the data do not determine (the rational terms' valley on a dozen views) are
    held near 0. The weight is fixed by this rule, not tuned on any set."""
    nd = len(param_names(model)) - 4
    if model not in REGULARISABLE:
        raise IntrinsicsError(f"the {model} model has no regularised solve; use one of {', '.join(REGULARISABLE)}")
    budget = n_measurements * REG_NORMAL_PIXEL_ERROR_PX**2 * REG_SHARE
    w = np.zeros(4 + nd)
    w[4:] = np.sqrt(budget / (nd * REG_NORMAL_DISTORTION**2))
    if model == "opencv8":
        w[4 + 5:4 + 8] *= REG_RATIONAL_FACTOR
    w[2:4] = np.sqrt(budget / (2 * REG_NORMAL_CENTRE_OFFSET_PX**2))
    at = np.zeros(4 + nd)
    at[2:4] = [(size[0] - 1) / 2.0, (size[1] - 1) / 2.0]
    return w, at


def intrinsic_steps(c: F64) -> F64:
    h = np.full(c.shape, 1e-7)
    h[:4] = 1e-5 * np.maximum(1.0, np.abs(c[:4]) * 1e-3)
    return h


@dataclass
class NormalEquations:
    """Normal equations of the bundle problem: totals, and the per-view blocks they sum."""

    A: F64
    B: F64   # (V, nc, 6)
    D: F64   # (V, 6, 6)
    gc: F64
    gv: F64  # (V, 6)
    Av: F64 | None = None   # (V, nc, nc): view v's share of A
    gcv: F64 | None = None  # (V, nc): view v's share of gc


def normal_equations_at(p: BundleProblem, c: F64, R: F64, t: F64, free: NDArray[np.bool_]
                        ) -> tuple[NormalEquations, F64]:
    """The normal equations over the ``free`` intrinsics and every pose, and the residuals."""
    Av, Bv, D, gcv, gv, _, r = kernels.normal_blocks(
        p.model_id, np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(R), np.ascontiguousarray(t),
        p.X, p.obs, p.weights(), p.starts)
    if p.prior_w is not None and p.prior_at is not None:
        # The prior's information and gradient, shared among the views in proportion to their kept
        # points (its weight is proportional to the count of measurements, ``regularisation``): a
        # leave-views-out replicate (influence, jackknife) is then the regularised solve of fewer views.
        n_v = np.add.reduceat((p.weights() > 0).astype(np.float64), p.starts[:-1]) if p.n_views else np.zeros(0)
        frac = n_v / max(float(n_v.sum()), 1.0)
        k = len(p.prior_w)
        w2 = p.prior_w ** 2
        Av = Av.copy()
        gcv = gcv.copy()
        idx = np.arange(k)
        Av[:, idx, idx] += frac[:, None] * w2[None, :]
        gcv[:, :k] += frac[:, None] * (w2 * (c[:k] - p.prior_at))[None, :]
    Av = Av[:, free][:, :, free]
    gcv = gcv[:, free]
    return NormalEquations(Av.sum(axis=0), Bv[:, free], D, gcv.sum(axis=0), gv, Av, gcv), r


def normal_equations(p: BundleProblem, r: F64, Jc: F64, Jp: F64) -> NormalEquations:
    """Normal equations from dense Jacobians (kept for callers that hold them)."""
    idx = 2 * p.starts[:-1]
    A = Jc.T @ Jc
    gc = Jc.T @ r
    D = np.add.reduceat(np.einsum("ri,rj->rij", Jp, Jp), idx, axis=0)
    B = np.add.reduceat(np.einsum("ri,rj->rij", Jc, Jp), idx, axis=0)
    gv = np.add.reduceat(Jp * r[:, None], idx, axis=0)
    return NormalEquations(A, B, D, gc, gv)


def solve_damped(n: NormalEquations, lam: float) -> tuple[F64, F64]:
    """The Marquardt-damped Gauss-Newton step for the arrow-structured normal equations: the poses
    are eliminated view by view (Schur complement, ``schur_kernels.schur_reduce``), the reduced intrinsics
    system is solved by a scaled least squares (rank-deficient directions get no step: LAPACK's
    gelsd, as ``np.linalg.lstsq``, called directly), then the poses are back-substituted. Returns
    ``(dc, dv)`` with ``dv`` (V, 6); NaN when the system is not finite (the caller treats it as a
    failed step). Compiled loops and one LAPACK call, not numba's ``np.linalg`` (whose bindings took
    20 s of CPU to compile on a cold cache, two thirds of the solver's)."""
    A, B, D = (np.ascontiguousarray(x, dtype=np.float64) for x in (n.A, n.B, n.D))
    gc, gv = np.ascontiguousarray(n.gc, dtype=np.float64), np.ascontiguousarray(n.gv, dtype=np.float64)
    nv, nc = D.shape[0], A.shape[0]
    Ss, rhs, Dinv, sc, status = schur_kernels.schur_reduce(A, B, D, gc, gv, float(lam))
    if status == 2:
        raise np.linalg.LinAlgError("Singular matrix: a view's damped pose block")
    if status == 1:
        return np.full(nc, np.nan), np.full((nv, 6), np.nan)
    dc = np.zeros(nc)
    if nc:
        dc = _lstsq(Ss, rhs) / sc
    return dc, schur_kernels.back_substitute(Dinv, B, gv, dc)


def _lstsq(a: F64, b: F64, rcond: float = 1e-14) -> F64:
    """``np.linalg.lstsq(a, b, rcond)[0]`` for a square ``a``: the same LAPACK routine (dgelsd) without
    numpy's wrapping, which cost more than the solve on the solver's ~10 x 10 systems."""
    m = a.shape[0]
    lwork, iwork, _ = lapack.dgelsd_lwork(m, m, 1, rcond)
    x, _, _, info = lapack.dgelsd(a, b, int(lwork), int(iwork), rcond)
    if info > 0:
        raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
    return np.asarray(x[:m], dtype=np.float64)


CHI2_TOL = 1e-6
"""Levenberg-Marquardt stops when a step lowers chi^2 by less than this."""


def cost_of(r: F64) -> float:
    return float(np.sum(r * r)) if np.all(np.isfinite(r)) else float("inf")


def levenberg_marquardt(p: BundleProblem, c: F64, R: F64, t: F64, free: NDArray[np.bool_], max_iter: int = 100
        ) -> tuple[F64, F64, F64, int]:
    """Levenberg-Marquardt (Marquardt's diagonal damping) with the Schur complement.

    ``max_iter`` bounds the walk along the rational model's flat valley: on few views its
    coefficients trade off (numerator against denominator) along a curved valley that LM
    follows for hundreds of iterations towards a degenerate optimum (k1 ~ -11, k4 ~ -11 on 6
    views) whose projection is *worse* than where the walk is stopped; geodesic acceleration
    (Transtrum & Sethna 2012) was tried and only walked further. The verdict flags such sets."""
    c, R, t = c.copy(), R.copy(), t.copy()
    r = p.residuals(c, R, t)
    cost = cost_of(r) + p.prior_cost(c)
    if not np.isfinite(cost):
        raise IntrinsicsError("the initial estimate puts target points behind the camera or outside "
                               "the lens model's range; check the target description")
    lam = 1e-3
    it = 0
    dof = max(len(r) - int(free.sum()) - 6 * p.n_views, 1)
    for it in range(1, max_iter + 1):  # noqa: B007
        n, _ = normal_equations_at(p, c, R, t, free)
        improved = False
        gain = 0.0
        near_gauss_newton = False
        while lam < 1e12:
            dc, dv = solve_damped(n, lam)
            c_new = c.copy()
            c_new[free] += dc
            R_new, t_new = kernels.moved_poses(R, t, dv)
            r_new = p.residuals(c_new, R_new, t_new)
            cost_new = cost_of(r_new) + p.prior_cost(c_new)
            if cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                gain = (cost - cost_new) / max(cost / dof, 1e-300)
                near_gauss_newton = lam <= 1e-2
                c, R, t, r, cost = c_new, R_new, t_new, r_new, cost_new
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        # Converged when the last step lowered chi^2 (cost over the residual variance) by less than
        # CHI2_TOL: the parameters are then within ~1e-3 sigma of the optimum, far below what
        # the data determine. A heavily damped step is small for another reason, so the test
        # applies only to steps close to Gauss-Newton.
        if not improved or rel < 1e-12 or (gain < CHI2_TOL and near_gauss_newton):
            break
    return c, R, t, it


def information_scale(S: F64) -> F64:
    """Square roots of the diagonal of a normal matrix, 1 where a parameter carries no information
    (dividing by its ~0 diagonal overflows)."""
    d = np.diag(S)
    big = float(np.max(np.abs(d))) if d.size else 0.0
    ok = np.isfinite(d) & (d > 1e-300 + 1e-15 * big)
    return np.where(ok, np.sqrt(np.where(ok, d, 1.0)), 1.0)


def marginals(n: NormalEquations) -> tuple[F64, F64]:
    """Inverse of the Schur complement (intrinsics covariance / sigma^2) and the pose blocks."""
    Dinv = np.linalg.inv(n.D)
    BDinv = n.B @ Dinv
    S = n.A - np.einsum("vij,vkj->ik", BDinv, n.B)
    s = information_scale(S)
    Ss = S / s[:, None] / s[None, :]
    lam, V = np.linalg.eigh(0.5 * (Ss + Ss.T))
    # A direction the data do not determine (eigenvalue below 1e-15 of the largest, or negative
    # from round-off at a degenerate optimum) gets the variance of that bound, not pinv's zero:
    # a rational fit to 5 views that ran into its pole reported 6e-8 px for a 0.4 px error.
    floor = 1e-15 * max(float(np.max(np.abs(lam))) if lam.size else 1.0, 1e-300)
    S_inv = (V / np.where(lam > floor, lam, floor)) @ V.T / s[:, None] / s[None, :]
    pose = Dinv + np.einsum("vji,jk,vkl->vil", BDinv, S_inv, BDinv)
    return S_inv, pose
