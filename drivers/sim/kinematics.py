"""A UR5e-class arm's kinematics with seeded errors: where the tool really is for a commanded pose.

A real arm's controller computes the tool pose from its joint angles through its *nominal*
kinematic model; the physical arm has slightly different link lengths and joint zero offsets, so
the physical tool pose differs from the reported one by millimetres, in a way that depends on the
pose (not i.i.d. noise). This module solves the nominal inverse kinematics for a commanded
``T_base_tool`` (metres) and applies the perturbed forward kinematics to the joints found.

Standard Denavit–Hartenberg parameters of the UR5e (metres, radians), as published by Universal
Robots. Our own small solver (scipy least squares from the previous joints) is enough: the
virtual cell needs one solution per move, near the last one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration import geometry as g
from drivers.errors import DriverInputError

UR5E_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
UR5E_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
UR5E_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
# An elbow-up, wrist-down configuration to start the first solve from.
Q_SEED = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])


class OutOfReach(DriverInputError):
    """No joint solution reaches the commanded pose."""


@dataclass(frozen=True)
class DH:
    """Denavit–Hartenberg parameters: ``d``, ``a`` (m), ``alpha`` (rad) and joint zero offsets (rad)."""

    d: NDArray[np.float64]
    a: NDArray[np.float64]
    alpha: NDArray[np.float64]
    theta_offset: NDArray[np.float64]

    def forward(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """``T_base_tool`` (4x4, m) for joints ``q`` (rad)."""
        T = np.eye(4)
        for i in range(6):
            th = q[i] + self.theta_offset[i]
            ct, st = np.cos(th), np.sin(th)
            ca, sa = np.cos(self.alpha[i]), np.sin(self.alpha[i])
            T = T @ np.array([[ct, -st * ca, st * sa, self.a[i] * ct],
                              [st, ct * ca, -ct * sa, self.a[i] * st],
                              [0.0, sa, ca, self.d[i]],
                              [0.0, 0.0, 0.0, 1.0]])
        return T


NOMINAL = DH(UR5E_D, UR5E_A, UR5E_ALPHA, np.zeros(6))


def perturbed(seed: int, link_sigma_mm: float, joint_offset_sigma_deg: float) -> DH:
    """The nominal arm with each ``d``/``a`` and joint zero offset perturbed (Gaussian, seeded)."""
    rng = np.random.default_rng(seed)
    dd = rng.normal(0.0, link_sigma_mm * 1e-3, 6)
    da = rng.normal(0.0, link_sigma_mm * 1e-3, 6)
    dth = rng.normal(0.0, np.radians(joint_offset_sigma_deg), 6)
    return DH(UR5E_D + dd, UR5E_A + da, UR5E_ALPHA, dth)


def _pose_error(T: NDArray[np.float64], target: NDArray[np.float64]) -> NDArray[np.float64]:
    dR = g.matrix_to_rotvec(target[:3, :3].T @ T[:3, :3])
    return np.concatenate([T[:3, 3] - target[:3, 3], 0.3 * dR])


def inverse(target: NDArray[np.float64], q_near: NDArray[np.float64], model: DH = NOMINAL) -> NDArray[np.float64]:
    """Joints (rad) that put ``model``'s tool at ``target``, the solution nearest ``q_near``."""
    for start in (q_near, Q_SEED):
        sol = least_squares(lambda q: _pose_error(model.forward(q), target), start, method="lm",
                            xtol=1e-12, ftol=1e-12)
        if np.max(np.abs(sol.fun)) < 1e-7:
            return np.asarray(sol.x, dtype=np.float64)
    x, y, z = target[:3, 3] * 1000.0
    raise OutOfReach(f"the arm cannot reach ({x:.0f}, {y:.0f}, {z:.0f}) mm with that orientation")


class KinematicError:
    """Commanded (nominal) pose -> joints -> true pose of the perturbed arm."""

    def __init__(self, seed: int, link_sigma_mm: float, joint_offset_sigma_deg: float) -> None:
        self.true_model = perturbed(seed, link_sigma_mm, joint_offset_sigma_deg)
        self._q = Q_SEED.copy()

    def solve(self, T_commanded: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(joints, true ``T_base_tool``) when the controller moves to ``T_commanded``."""
        q = inverse(np.asarray(T_commanded, dtype=np.float64), self._q)
        self._q = q
        return q, self.true_model.forward(q)
