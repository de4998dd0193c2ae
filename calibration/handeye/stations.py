"""The sparse reprojection problem the special hand-eye solvers share (4-DOF, measured frame).

Every target point of every station is reprojected through the hand-eye chain
``C_i = inv(X) · H_i · Z`` (``H_i = inv(G_i)`` eye-in-hand, ``G_i`` eye-to-hand; ``G_i = T_base_tool``,
``C_i = T_cam_target``; metres, radians), where ``G_i`` is the recorded robot pose with a small
correction of its own (rotation vector in the base frame and translation, 6 per station) that
the robot's stated noise holds with a Gaussian prior: the maximum-likelihood form of
``calibration.handeye``. A solver says how its leading parameters give ``X`` and ``Z`` (``lead``)
and, if they have one, their own prior rows (``lead_prior``).

Parameters: the ``n_lead`` leading ones, then 6 per station. Residuals: the pixels (2 per point,
divided by ``sigma_px``), the leading prior rows, the stations' rotation priors (3 each), their
translation priors (3 each). The Jacobian uses the structure: forward differences over the
leading parameters, 6 evaluations for all station corrections at once (station ``k``'s pixels
depend only on its own correction), the prior rows exact.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import invert
from calibration.handeye.model import RobotNoise

Mat4 = NDArray[np.float64]
F64 = NDArray[np.float64]
STEP: float = 1e-7


class StationData(Protocol):
    """What the problem reads of a station (``calibration.handeye.dof4.Station4``)."""

    G: Mat4
    obj: F64
    uv: F64


class StationProblem:
    """Reprojection with leading parameters and per-station robot corrections (module docstring)."""

    n_lead: int = 0

    def __init__(self, setup: str, stations: Sequence[StationData], camera: CameraModel, sigma_px: float,
                 noise: RobotNoise) -> None:
        self.setup, self.camera, self.sigma_px = setup, camera, sigma_px
        self.sig_r, self.sig_t = np.radians(noise.sigma_deg), noise.sigma_mm * 1e-3
        self.G = np.array([s.G for s in stations])
        self.n = len(stations)
        self.obj = np.vstack([s.obj for s in stations])
        self.uv = np.vstack([s.uv for s in stations])
        self.sid = np.concatenate([np.full(len(s.obj), k) for k, s in enumerate(stations)])

    # -- what a solver fills in -------------------------------------------------------------------
    def lead(self, x: F64) -> tuple[Mat4, Mat4]:
        """``X`` and ``Z`` from the leading parameters ``x[:n_lead]``."""
        raise NotImplementedError

    def lead_prior(self, x: F64) -> F64:
        """Prior rows of the leading parameters (whitened); none by default."""
        return np.zeros(0)

    def lead_prior_jacobian(self) -> F64:
        """``(rows, n_lead)`` derivative of :meth:`lead_prior` (constant: the priors are linear)."""
        return np.zeros((0, self.n_lead))

    # -- the shared problem -----------------------------------------------------------------------
    def corrections(self, x: F64) -> F64:
        return x[self.n_lead:].reshape(self.n, 6)

    def poses(self, x: F64) -> tuple[Mat4, Mat4, F64]:
        """``X``, ``Z`` and the corrected robot poses ``(n, 4, 4)``."""
        X, Z = self.lead(x)
        d = self.corrections(x)
        Gc = self.G.copy()
        Gc[:, :3, :3] = Rotation.from_rotvec(d[:, :3]).as_matrix() @ self.G[:, :3, :3]
        Gc[:, :3, 3] = self.G[:, :3, 3] + d[:, 3:]
        return X, Z, Gc

    def residuals(self, x: F64) -> F64:
        X, Z, Gc = self.poses(x)
        H = Gc if self.setup == "eye-to-hand" else np.array([invert(g) for g in Gc])
        C = np.einsum("ij,njk,kl->nil", invert(X), H, Z)[self.sid]
        P = np.einsum("nij,nj->ni", C[:, :3, :3], self.obj) + C[:, :3, 3]
        r = np.nan_to_num((self.camera.project(P) - self.uv).ravel() / self.sigma_px, nan=1e6)
        d = self.corrections(x)
        return np.concatenate([r, self.lead_prior(x), d[:, :3].ravel() / self.sig_r, d[:, 3:].ravel() / self.sig_t])

    def jacobian(self, x: F64) -> F64:
        r0 = self.residuals(x)
        n_px = 2 * len(self.obj)
        L = self.n_lead
        J = np.zeros((len(r0), len(x)))
        for a in range(L):
            xp = x.copy()
            xp[a] += STEP
            J[:n_px, a] = (self.residuals(xp)[:n_px] - r0[:n_px]) / STEP
        rows = np.repeat(self.sid, 2)
        for a in range(6):
            xp = x.copy()
            xp[L + a:: 6] += STEP
            J[np.arange(n_px), L + 6 * rows + a] = (self.residuals(xp)[:n_px] - r0[:n_px]) / STEP
        Jl = self.lead_prior_jacobian()
        J[n_px: n_px + len(Jl), :L] = Jl
        base = n_px + len(Jl)
        k = np.arange(self.n)
        J[base + 3 * k[:, None] + np.arange(3), L + 6 * k[:, None] + np.arange(3)] = 1.0 / self.sig_r
        J[base + 3 * self.n + 3 * k[:, None] + np.arange(3), L + 3 + 6 * k[:, None] + np.arange(3)] = 1.0 / self.sig_t
        return J
