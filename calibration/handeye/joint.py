"""Joint maximum-likelihood refinement over X, Z and per-station robot pose corrections (ours)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import (
    exp_so3,
    invert,
)
from calibration.handeye.frames import perturb, predict_cam_target
from calibration.handeye.model import (
    Mat4,
    RobotNoise,
    Station,
)
from calibration.intrinsics import camera_from_vector, intrinsic_steps, intrinsics_vector

SYSTEMATIC_PRIOR: Final = 0.01
"""1-sigma prior of each entry of the systematic position correction ``A`` (1 % = 10 mm per metre):
weak, only to keep the solve regular when the stations do not span all directions."""


@dataclass(frozen=True)
class JointOptions:
    """What the joint refinement estimates besides X, Z and the per-station corrections.

    ``systematic``: a pose-dependent robot position error, ``t_true = t_rec + A (t_rec - t_mean)``
    (``A`` 3x3, base frame: link-length scale and shear errors to first order over the
    workspace) — it predicts at new stations, unlike i.i.d. corrections.
    ``intrinsics``: the camera's intrinsics refined jointly (additive ``c = c0 + dc``), with a
    Gaussian prior from ``camera_covariance`` (the intrinsics result's) when given.
    ``exact_robot``: no per-station corrections — the recorded robot poses are taken as exact and
    only the pixel residuals are minimised (the plain joint reprojection refinement). Its fit
    minimises the same quantity a held-out station is judged by (pixels predicted from the
    recorded pose), which is why it can predict better on an arm whose error is pose-dependent
    millimetres, where per-station corrections under a small i.i.d. prior are the wrong model.
    """

    systematic: bool = False
    intrinsics: bool = False
    camera_covariance: NDArray[np.float64] | None = None
    exact_robot: bool = False


class JointProblem:
    """Maximum-likelihood refinement over X, Z, per-station robot pose corrections and (options)
    the camera intrinsics and a systematic robot error.

    Parameters: ``[X (6), Z (6), dc (n_cam), A (n_sys), station corrections (6 n)]``; residuals:
    weighted pixel residuals over ``sigma_px``, then the corrections' priors (orientation rows,
    position rows), then the priors of ``A`` and ``dc``.
    """

    def __init__(self, setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float,
                 noise: RobotNoise, X0: Mat4, Z0: Mat4, options: JointOptions | None = None) -> None:
        self.setup, self.camera, self.sigma_px = setup, camera, sigma_px
        self.stations, self.noise = list(stations), noise
        self.options = options or JointOptions()
        self.sig_t = noise.sigma_mm * 1e-3
        self.sig_r = np.radians(noise.sigma_deg)
        self.X0, self.Z0 = X0, Z0
        self.G = np.array([s.G for s in stations])
        self.n = len(stations)
        self.obj = np.vstack([s.obj for s in stations])
        self.uv = np.vstack([s.uv for s in stations])
        self.w = np.concatenate([np.ones(len(s.obj)) if s.w is None else s.w for s in stations])
        self.sid = np.concatenate([np.full(len(s.obj), k) for k, s in enumerate(stations)])
        self.n_obs = len(self.obj)
        self.c0 = intrinsics_vector(camera)
        self.n_cam = len(self.c0) if self.options.intrinsics else 0
        self.n_sys = 9 if self.options.systematic else 0
        self.k0 = 12 + self.n_cam + self.n_sys
        """Index of the first per-station correction."""
        self.n_d = 0 if self.options.exact_robot else self.n
        """Stations with a pose correction (0 for the exact-robot model)."""
        self.n_params = self.k0 + 6 * self.n_d
        self.t_mean = self.G[:, :3, 3].mean(axis=0)
        self.cam_white: NDArray[np.float64] | None = None
        cov = self.options.camera_covariance
        if self.n_cam and cov is not None and np.shape(cov) == (self.n_cam, self.n_cam):
            c = np.asarray(cov, dtype=np.float64)
            c = c + np.diag(np.maximum(np.diag(c), 1e-12) * 1e-9)
            self.cam_white = np.linalg.cholesky(np.linalg.inv(c)).T

    def camera_at(self, x: NDArray[np.float64]) -> CameraModel:
        if not self.n_cam:
            return self.camera
        return camera_from_vector(self.camera.model, self.camera.size, self.c0 + x[12:12 + self.n_cam])

    def systematic_matrix(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        if not self.n_sys:
            return np.zeros((3, 3))
        return x[12 + self.n_cam:self.k0].reshape(3, 3)

    def corrected(self, G: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Recorded robot poses (N, 4, 4) with the systematic correction of ``x`` applied."""
        if not self.n_sys:
            return G
        out = G.copy()
        out[:, :3, 3] = G[:, :3, 3] + (G[:, :3, 3] - self.t_mean) @ self.systematic_matrix(x).T
        return out

    def corrections(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """(n, 6) per-station corrections: orientation (rad), position (m); zeros for the exact robot."""
        if not self.n_d:
            return np.zeros((self.n, 6))
        return x[self.k0:].reshape(self.n, 6)

    def poses(self, x: NDArray[np.float64]) -> tuple[Mat4, Mat4, NDArray[np.float64]]:
        X = perturb(self.X0, x[0:6])
        Z = perturb(self.Z0, x[6:12])
        d = self.corrections(x)
        Gs = self.corrected(self.G, x)
        Gc = Gs.copy()
        Gc[:, :3, :3] = exp_so3(d[:, :3]) @ Gs[:, :3, :3]
        Gc[:, :3, 3] = Gs[:, :3, 3] + d[:, 3:]
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
        e = (self.camera_at(x).project(P) - self.uv) * self.w[:, None]
        r_px = e.ravel() / self.sigma_px
        parts = [np.nan_to_num(r_px, nan=1e6)]
        if self.n_d:
            d = self.corrections(x)
            parts += [d[:, :3].ravel() / self.sig_r, d[:, 3:].ravel() / self.sig_t]
        if self.n_sys:
            parts.append(x[12 + self.n_cam:self.k0] / SYSTEMATIC_PRIOR)
        if self.cam_white is not None:
            parts.append(self.cam_white @ x[12:12 + self.n_cam])
        return np.concatenate(parts)

    def _steps(self) -> NDArray[np.float64]:
        h = np.full(self.k0, 1e-7)
        if self.n_cam:
            h[12:12 + self.n_cam] = intrinsic_steps(self.c0)
        return h

    def jacobian(self, x: NDArray[np.float64], r0: NDArray[np.float64]) -> NDArray[np.float64]:
        """Forward differences exploiting the structure: one evaluation per global parameter (X, Z,
        intrinsics, systematic), and 6 for all station corrections at once (station k's residuals
        depend only on its own correction)."""
        h = 1e-7
        J = np.zeros((len(r0), len(x)))
        for a, ha in enumerate(self._steps()):
            xp = x.copy()
            xp[a] += ha
            J[:, a] = (self.residuals(xp) - r0) / ha
        rows_px = np.repeat(self.sid, 2)
        n_px = 2 * self.n_obs
        k0 = self.k0
        for a in range(6 if self.n_d else 0):
            xp = x.copy()
            xp[k0 + a :: 6] += h
            col = (self.residuals(xp) - r0) / h
            for k in range(self.n):
                sel = np.flatnonzero(rows_px == k)
                J[sel, k0 + 6 * k + a] = col[sel]
            prior_row = n_px + (3 * self.n + 3 * np.arange(self.n) + a - 3 if a >= 3 else 3 * np.arange(self.n) + a)
            J[prior_row, k0 + 6 * np.arange(self.n) + a] = col[prior_row]
        return J

    def solve(self, x0: NDArray[np.float64] | None = None, max_iter: int = 50) -> LMResult:
        """Levenberg-Marquardt (dense normal equations; a few hundred parameters at most)."""
        x = np.zeros(self.n_params) if x0 is None else x0.copy()
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

    def predict(self, x: NDArray[np.float64], G: Mat4, obj: NDArray[np.float64]) -> tuple[Mat4, NDArray[np.float64]]:
        """Predicted ``T_cam_target`` and pixels of ``obj`` for a new station with recorded robot pose
        ``G`` (systematic correction applied, no i.i.d. correction: it is unknown there)."""
        X, Z, _ = self.poses(x)
        Gs = self.corrected(G[None], x)[0]
        Cp = predict_cam_target(self.setup, X, Z, Gs)
        return Cp, self.camera_at(x).project(obj @ Cp[:3, :3].T + Cp[:3, 3])


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
        cols = job.k0 + 6 * np.repeat(np.arange(n), 3) + 3 * g + np.tile(np.arange(3), n)
        h = J[rows, cols] ** 2 * Ninv[cols, cols]
        red = max(float(np.sum(1.0 - h)), 1e-9)
        factor = float(res.fun[rows] @ res.fun[rows]) / red
        out.append(sig * np.sqrt(max(factor, 1e-6)))
    return RobotNoise(sigma_mm=max(float(out[1]) * 1e3, 1e-4), sigma_deg=max(float(np.degrees(out[0])), 1e-5))


def refine(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float, noise: RobotNoise,
           X0: Mat4, Z0: Mat4, options: JointOptions | None = None) -> tuple[JointProblem, LMResult]:
    """Solve, then re-linearise once at the solution (the small-angle parametrisation of X and Z
    stays accurate); the additive intrinsics / systematic / station parameters carry over."""
    job = JointProblem(setup, stations, camera, sigma_px, noise, X0, Z0, options)
    res = job.solve()
    X, Z, _ = job.poses(res.x)
    job2 = JointProblem(setup, stations, camera, sigma_px, noise, X, Z, options)
    x1 = res.x.copy()
    x1[:12] = 0.0
    res2 = job2.solve(x1)
    return job2, res2
