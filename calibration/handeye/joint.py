"""Joint maximum-likelihood refinement over X, Z and per-station robot pose corrections (ours)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import (
    exp_so3,
    invert,
)
from calibration.handeye.frames import (
    perturb,
)
from calibration.handeye.model import (
    Mat4,
    RobotNoise,
    Station,
)


# --------------------------------------------------------------------------------------------
# joint refinement
# --------------------------------------------------------------------------------------------
class JointProblem:
    """Maximum-likelihood refinement over X, Z and per-station robot pose corrections."""

    def __init__(self, setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float,
                 noise: RobotNoise, X0: Mat4, Z0: Mat4) -> None:
        self.setup, self.camera, self.sigma_px = setup, camera, sigma_px
        self.sig_t = noise.sigma_mm * 1e-3
        self.sig_r = np.radians(noise.sigma_deg)
        self.X0, self.Z0 = X0, Z0
        self.G = np.array([s.G for s in stations])
        self.n = len(stations)
        self.obj = np.vstack([s.obj for s in stations])
        self.uv = np.vstack([s.uv for s in stations])
        self.sid = np.concatenate([np.full(len(s.obj), k) for k, s in enumerate(stations)])
        self.n_obs = len(self.obj)

    def poses(self, x: NDArray[np.float64]) -> tuple[Mat4, Mat4, NDArray[np.float64]]:
        X = perturb(self.X0, x[0:6])
        Z = perturb(self.Z0, x[6:12])
        d = x[12:].reshape(self.n, 6)
        Rd = exp_so3(d[:, :3])
        Gc = self.G.copy()
        Gc[:, :3, :3] = Rd @ self.G[:, :3, :3]
        Gc[:, :3, 3] = self.G[:, :3, 3] + d[:, 3:]
        return X, Z, Gc

    def cam_target(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        X, Z, Gc = self.poses(x)
        Xi = invert(X)
        if self.setup == "eye-to-hand":
            Hinv = Gc
        else:
            Hinv = np.zeros_like(Gc)
            Rt = np.transpose(Gc[:, :3, :3], (0, 2, 1))
            Hinv[:, :3, :3] = Rt
            Hinv[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, Gc[:, :3, 3])
            Hinv[:, 3, 3] = 1.0
        return np.einsum("ij,njk,kl->nil", Xi, Hinv, Z)

    def residuals(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        C = self.cam_target(x)
        Cs = C[self.sid]
        P = np.einsum("nij,nj->ni", Cs[:, :3, :3], self.obj) + Cs[:, :3, 3]
        r_px = (self.camera.project(P) - self.uv).ravel() / self.sigma_px
        d = x[12:].reshape(self.n, 6)
        prior = np.concatenate([d[:, :3].ravel() / self.sig_r, d[:, 3:].ravel() / self.sig_t])
        return np.concatenate([np.nan_to_num(r_px, nan=1e6), prior])

    def jacobian(self, x: NDArray[np.float64], r0: NDArray[np.float64]) -> NDArray[np.float64]:
        """Forward differences exploiting the structure: 12 evaluations for X and Z, and 6 for all
        station corrections at once (station k's residuals depend only on its own correction)."""
        h = 1e-7
        J = np.zeros((len(r0), len(x)))
        for a in range(12):
            xp = x.copy()
            xp[a] += h
            J[:, a] = (self.residuals(xp) - r0) / h
        rows_px = np.repeat(self.sid, 2)
        n_px = 2 * self.n_obs
        for a in range(6):
            xp = x.copy()
            xp[12 + a :: 6] += h
            col = (self.residuals(xp) - r0) / h
            for k in range(self.n):
                sel = np.flatnonzero(rows_px == k)
                J[sel, 12 + 6 * k + a] = col[sel]
            prior_row = n_px + (3 * self.n + 3 * np.arange(self.n) + a - 3 if a >= 3 else 3 * np.arange(self.n) + a)
            J[prior_row, 12 + 6 * np.arange(self.n) + a] = col[prior_row]
        return J

    def solve(self, x0: NDArray[np.float64] | None = None, max_iter: int = 50) -> LMResult:
        """Levenberg-Marquardt (dense normal equations; a few hundred parameters at most)."""
        x = np.zeros(12 + 6 * self.n) if x0 is None else x0.copy()
        r = self.residuals(x)
        cost = float(r @ r)
        lam = 1e-3
        J = self.jacobian(x, r)
        for _ in range(max_iter):
            # einsum, not BLAS: multithreaded BLAS spin-waits badly on a loaded 2-core machine
            A = np.einsum("ij,ik->jk", J, J)
            g = np.einsum("ij,i->j", J, r)
            improved = False
            for _ in range(12):
                dx = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
                rn = self.residuals(x + dx)
                cn = float(rn @ rn)
                if cn < cost:
                    improved = True
                    break
                lam *= 10.0
            if not improved:
                break
            x = x + dx
            rel = (cost - cn) / max(cost, 1e-300)
            r, cost = rn, cn
            lam = max(lam / 10.0, 1e-9)
            J = self.jacobian(x, r)
            if rel < 1e-10:
                break
        return LMResult(x=x, fun=r, jac=J, cost=0.5 * cost)


@dataclass
class LMResult:
    x: NDArray[np.float64]
    fun: NDArray[np.float64]
    jac: NDArray[np.float64]
    cost: float


def vce_robot_noise(job: JointProblem, res: LMResult, noise: RobotNoise) -> RobotNoise:
    """One variance-component step for the two robot groups (orientation, position).

    Each prior row has one non-zero, so its leverage is ``J_ii² (JᵀJ)⁻¹_cc``; the group's new
    variance is the old one times ``Σ r² / Σ (1 - h)`` (Förstner's estimator)."""
    J = res.jac
    Ninv = np.linalg.inv(np.einsum("ij,ik->jk", J, J))
    base = 2 * job.n_obs
    n = job.n
    out = []
    for g, sig in ((0, np.radians(noise.sigma_deg)), (1, noise.sigma_mm * 1e-3)):
        rows = base + 3 * n * g + np.arange(3 * n)
        cols = 12 + 6 * np.repeat(np.arange(n), 3) + 3 * g + np.tile(np.arange(3), n)
        h = J[rows, cols] ** 2 * Ninv[cols, cols]
        red = max(float(np.sum(1.0 - h)), 1e-9)
        factor = float(res.fun[rows] @ res.fun[rows]) / red
        out.append(sig * np.sqrt(max(factor, 1e-6)))
    return RobotNoise(sigma_mm=max(float(out[1]) * 1e3, 1e-4), sigma_deg=max(float(np.degrees(out[0])), 1e-5))


def refine(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float, noise: RobotNoise,
            X0: Mat4, Z0: Mat4) -> tuple[JointProblem, Any]:
    job = JointProblem(setup, stations, camera, sigma_px, noise, X0, Z0)
    res = job.solve()
    # Re-linearise once at the solution (small-angle parametrisation stays accurate).
    X, Z, _ = job.poses(res.x)
    job2 = JointProblem(setup, stations, camera, sigma_px, noise, X, Z)
    x1 = res.x.copy()
    x1[:12] = 0.0
    res2 = job2.solve(x1)
    return job2, res2
