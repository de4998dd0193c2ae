"""The vectorised projection model and our Levenberg-Marquardt bundle solver (Schur complement)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.camera_model import CameraModel, ModelName, distort_normalized
from calibration.geometry import exp_so3
from calibration.intrinsics.results import (
    F64,
    CalibrationError,
)

# --------------------------------------------------------------------------------------------
# the vectorised model


def param_names(model: str) -> list[str]:
    names = {"opencv5": ["k1", "k2", "p1", "p2", "k3"],
             "opencv8": ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"],
             "division": ["kappa"]}[model]
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

    @property
    def n_views(self) -> int:
        return len(self.starts) - 1

    def project(self, c: F64, R: F64, t: F64) -> F64:
        P = np.einsum("mij,mj->mi", R[self.view], self.X) + t[self.view]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / P[:, 2:3]
        xy[P[:, 2] <= 0] = np.nan
        return project_normalized(self.model, c, xy)

    def residuals(self, c: F64, R: F64, t: F64) -> F64:
        """Weighted pixel residuals (the solver's cost): ``w_i (projected - observed)``, flattened."""
        r = self.project(c, R, t) - self.obs
        if self.w is not None:
            r = r * self.w[:, None]
        return r.reshape(-1)


def intrinsic_steps(c: F64) -> F64:
    h = np.full(c.shape, 1e-7)
    h[:4] = 1e-5 * np.maximum(1.0, np.abs(c[:4]) * 1e-3)
    return h


def jacobians(p: BundleProblem, c: F64, R: F64, t: F64, free: NDArray[np.bool_]) -> tuple[F64, F64]:
    """Central-difference Jacobians: (2M, n_free) for the intrinsics, (2M, 6) for each row's pose.

    The pose columns of all views are perturbed at once (a view's residuals depend only on its
    own pose), so the cost is 2 * (n_free + 6) residual evaluations whatever the view count.
    Rotations are perturbed on the left: ``R <- exp(w) R``.
    """
    hs = intrinsic_steps(c)
    cols = []
    for i in np.nonzero(free)[0]:
        e = np.zeros_like(c)
        e[i] = hs[i]
        cols.append((p.residuals(c + e, R, t) - p.residuals(c - e, R, t)) / (2 * hs[i]))
    Jc = np.column_stack(cols) if cols else np.zeros((2 * len(p.X), 0))
    Jp = np.empty((2 * len(p.X), 6))
    hr, ht = 1e-7, 1e-7
    for k in range(3):
        w = np.zeros(3)
        w[k] = hr
        Rp = exp_so3(w[None])[0] @ R
        Rm = exp_so3(-w[None])[0] @ R
        Jp[:, k] = (p.residuals(c, Rp, t) - p.residuals(c, Rm, t)) / (2 * hr)
    for k in range(3):
        e3 = np.zeros(3)
        e3[k] = ht
        Jp[:, 3 + k] = (p.residuals(c, R, t + e3) - p.residuals(c, R, t - e3)) / (2 * ht)
    return Jc, Jp


@dataclass
class NormalEquations:
    A: F64
    B: F64   # (V, nc, 6)
    D: F64   # (V, 6, 6)
    gc: F64
    gv: F64  # (V, 6)


def normal_equations(p: BundleProblem, r: F64, Jc: F64, Jp: F64) -> NormalEquations:
    idx = 2 * p.starts[:-1]
    A = Jc.T @ Jc
    gc = Jc.T @ r
    D = np.add.reduceat(np.einsum("ri,rj->rij", Jp, Jp), idx, axis=0)
    B = np.add.reduceat(np.einsum("ri,rj->rij", Jc, Jp), idx, axis=0)
    gv = np.add.reduceat(Jp * r[:, None], idx, axis=0)
    return NormalEquations(A, B, D, gc, gv)


def solve_damped(n: NormalEquations, lam: float) -> tuple[F64, F64]:
    A = n.A + lam * np.diag(np.diag(n.A))
    dD = np.einsum("vii->vi", n.D)
    D = n.D + lam * dD[:, :, None] * np.eye(6)[None]
    Dinv = np.linalg.inv(D)
    BDinv = n.B @ Dinv
    S = A - np.einsum("vij,vkj->ik", BDinv, n.B)
    rhs = -n.gc + np.einsum("vij,vj->i", BDinv, n.gv)
    if S.size:
        s = np.sqrt(np.maximum(np.diag(S), 1e-300))
        dc = np.linalg.lstsq(S / s[:, None] / s[None, :], rhs / s, rcond=1e-14)[0] / s
    else:
        dc = np.zeros(0)
    dv = np.einsum("vij,vj->vi", Dinv, -n.gv - np.einsum("vji,j->vi", n.B, dc))
    return dc, dv


def cost_of(r: F64) -> float:
    return float(np.sum(r * r)) if np.all(np.isfinite(r)) else float("inf")


def levenberg_marquardt(p: BundleProblem, c: F64, R: F64, t: F64, free: NDArray[np.bool_], max_iter: int = 100
        ) -> tuple[F64, F64, F64, int]:
    """Levenberg-Marquardt (Marquardt's diagonal damping) with the Schur complement."""
    c, R, t = c.copy(), R.copy(), t.copy()
    r = p.residuals(c, R, t)
    cost = cost_of(r)
    if not np.isfinite(cost):
        raise CalibrationError("the initial estimate puts target points behind the camera or outside "
                               "the lens model's range; check the target description")
    lam = 1e-3
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        Jc, Jp = jacobians(p, c, R, t, free)
        n = normal_equations(p, r, Jc, Jp)
        improved = False
        while lam < 1e12:
            dc, dv = solve_damped(n, lam)
            c_new = c.copy()
            c_new[free] += dc
            R_new = exp_so3(dv[:, :3]) @ R
            t_new = t + dv[:, 3:]
            r_new = p.residuals(c_new, R_new, t_new)
            cost_new = cost_of(r_new)
            if cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                c, R, t, r, cost = c_new, R_new, t_new, r_new, cost_new
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved or rel < 1e-12:
            break
    return c, R, t, it


def marginals(n: NormalEquations) -> tuple[F64, F64]:
    """Inverse of the Schur complement (intrinsics covariance / sigma^2) and the pose blocks."""
    Dinv = np.linalg.inv(n.D)
    BDinv = n.B @ Dinv
    S = n.A - np.einsum("vij,vkj->ik", BDinv, n.B)
    s = np.sqrt(np.maximum(np.diag(S), 1e-300))
    S_inv = np.linalg.pinv(S / s[:, None] / s[None, :], rcond=1e-15) / s[:, None] / s[None, :]
    pose = Dinv + np.einsum("vji,jk,vkl->vil", BDinv, S_inv, BDinv)
    return S_inv, pose
