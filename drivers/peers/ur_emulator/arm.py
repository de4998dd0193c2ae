"""The emulated UR5e arm: its kinematics, modes and the motion of ``moveL`` / ``moveJ``.

Units: joints in radians, poses ``T_base_tool`` 4x4 in metres (UR pose vectors: metres and a
rotation vector in radians), speeds in m/s and rad/s, times in seconds of ``time.monotonic``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

# robot modes (RTDE robot_mode) and safety modes
ROBOT_MODE_POWER_ON = 4
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL = 1
SAFETY_PROTECTIVE_STOP = 3
ROBOT_MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
                    3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING"}

# UR5e DH parameters (Universal Robots' published values)
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
HOME_Q = (0.0, -1.9, 1.9, -1.5708, -1.5708, 0.0)


def forward_kinematics(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """UR5e flange pose ``T_base_tool`` (4x4, metres) for joint angles ``q`` (radians)."""
    T = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct],
                          [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    return T


def pose_to_T(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """A UR pose vector (x, y, z in m, rotation vector in rad) as a 4x4 transform."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:6]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def T_to_pose(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """A 4x4 transform as a UR pose vector (x, y, z in m, rotation vector in rad)."""
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def inverse_kinematics(T_target: NDArray[np.float64],
                       q_near: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Joint angles near ``q_near`` that reach ``T_target``, or None when it is out of reach."""
    R_target = Rotation.from_matrix(T_target[:3, :3])

    def residual(q: NDArray[np.float64]) -> NDArray[np.float64]:
        T = forward_kinematics(q)
        rot_err = (R_target.inv() * Rotation.from_matrix(T[:3, :3])).as_rotvec()
        return np.concatenate([T[:3, 3] - T_target[:3, 3], 0.2 * rot_err])

    sol = least_squares(residual, np.asarray(q_near, dtype=np.float64), method="lm", xtol=1e-12, ftol=1e-12)
    if not sol.success or np.max(np.abs(residual(sol.x))) > 1e-6:
        return None
    q: NDArray[np.float64] = sol.x
    return q


@dataclass
class Motion:
    """One move in progress: from (q_start, T_start) at ``t0`` to (q_end, T_end) in ``duration_s``."""

    kind: str  # "linear" or "joint"
    t0: float
    duration_s: float
    q_start: NDArray[np.float64]
    q_end: NDArray[np.float64]
    T_start: NDArray[np.float64]
    T_end: NDArray[np.float64]
    waiting_client: bool  # a synchronous command: signal done when finished


@dataclass
class Arm:
    """The arm's joints, pose, modes, motion and digital outputs (the controller holds the lock)."""

    q: NDArray[np.float64] = field(default_factory=lambda: np.array(HOME_Q, dtype=np.float64))
    robot_mode: int = ROBOT_MODE_RUNNING
    safety_mode: int = SAFETY_NORMAL
    motion: Motion | None = None
    digital_out: int = 0
    config_out: int = 0
    tool_out: int = 0
    speed_slider: float = 1.0
    moves_completed: int = 0
    last_move: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.T = forward_kinematics(self.q)

    @property
    def powered(self) -> bool:
        return self.robot_mode in (ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE, 6, ROBOT_MODE_RUNNING)

    @property
    def ready(self) -> bool:
        """Running and in normal safety: the control script may run."""
        return self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_NORMAL

    def joint_speeds(self) -> tuple[float, ...]:
        m = self.motion
        if m is None or m.duration_s <= 0:
            return (0.0,) * 6
        return tuple(float(v) for v in (m.q_end - m.q_start) / m.duration_s)

    def tcp_speed(self) -> tuple[float, ...]:
        m = self.motion
        if m is None or m.duration_s <= 0:
            return (0.0,) * 6
        v = (m.T_end[:3, 3] - m.T_start[:3, 3]) / m.duration_s
        return (float(v[0]), float(v[1]), float(v[2]), 0.0, 0.0, 0.0)

    def halt(self) -> None:
        """Stop where the arm is (stopL / stopJ / protective stop): a waiting command gets no "done"."""
        self.motion = None

    def protective_stop(self) -> None:
        self.halt()
        self.safety_mode = SAFETY_PROTECTIVE_STOP

    def start_linear(self, pose: NDArray[np.float64], speed_m_s: float, now: float, waiting: bool) -> bool:
        """Start ``moveL`` to a UR pose vector; False when the target is invalid or unreachable."""
        if not (np.all(np.isfinite(pose)) and math.isfinite(speed_m_s) and speed_m_s > 0):
            return False
        T_end = pose_to_T(pose)
        q_end = inverse_kinematics(T_end, self.q)
        if q_end is None:
            return False
        dist = float(np.linalg.norm(T_end[:3, 3] - self.T[:3, 3]))
        angle = float(np.linalg.norm((Rotation.from_matrix(self.T[:3, :3]).inv()
                                      * Rotation.from_matrix(T_end[:3, :3])).as_rotvec()))
        duration = max(dist / (speed_m_s * self.speed_slider), angle / 1.0, 0.0)
        self.motion = Motion("linear", now, duration, self.q.copy(), q_end, self.T.copy(), T_end, waiting)
        self.last_move = {"kind": "moveL", "pose": pose.tolist(), "speed": speed_m_s}
        return True

    def start_joint(self, q_end: NDArray[np.float64], speed_rad_s: float, now: float, waiting: bool) -> bool:
        """Start ``moveJ`` to joint angles ``q_end``; False when the target or speed is invalid."""
        if not (np.all(np.isfinite(q_end)) and math.isfinite(speed_rad_s) and speed_rad_s > 0):
            return False
        duration = float(np.max(np.abs(q_end - self.q))) / (speed_rad_s * self.speed_slider)
        T_end = forward_kinematics(q_end)
        self.motion = Motion("joint", now, duration, self.q.copy(), q_end.copy(), self.T.copy(), T_end,
                             waiting)
        self.last_move = {"kind": "moveJ", "q": q_end.tolist(), "speed": speed_rad_s}
        return True

    def step(self, now: float) -> Motion | None:
        """Advance the motion to ``now``; the motion that finished in this step, if any."""
        m = self.motion
        if m is None:
            return None
        s = 1.0 if m.duration_s <= 0 else min(1.0, (now - m.t0) / m.duration_s)
        self.q = m.q_start + s * (m.q_end - m.q_start)
        if m.kind == "linear":
            T = np.eye(4)
            T[:3, 3] = m.T_start[:3, 3] + s * (m.T_end[:3, 3] - m.T_start[:3, 3])
            rots = Rotation.from_matrix(np.stack([m.T_start[:3, :3], m.T_end[:3, :3]]))
            T[:3, :3] = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
            self.T = T
        else:
            self.T = forward_kinematics(self.q)
        if s < 1.0:
            return None
        self.T = m.T_end.copy()
        self.q = m.q_end.copy()
        self.motion = None
        self.moves_completed += 1
        return m
