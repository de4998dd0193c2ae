"""The emulated UR5e arm: its kinematics, modes and the motion of ``moveL`` / ``moveJ``.

``moveL`` moves as a UR controller's ``movel(pose, a, v)`` does (``drivers.robot.ur_movel``, which says where
that comes from): trapezoidal profiles for the position (``v``, ``a``) and the orientation (4 ``v`` rad/s held
to the UR5e's 180 deg/s joints, 4 ``a`` rad/s^2), the longer setting the time; the tool travels the straight
line (orientation by slerp) along that profile. A servo step (``servoL``) reaches its pose in the step's time
at constant speed; ``moveJ`` moves every joint at constant speed.

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

from drivers.robot.ur_movel import movel_profile, profile_fraction

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


def _pose_error(T: NDArray[np.float64], T_target: NDArray[np.float64]) -> NDArray[np.float64]:
    """Position (m) and rotation-vector (rad) error of ``T`` against ``T_target``, base frame."""
    R = T_target[:3, :3] @ T[:3, :3].T  # small near the solution: its skew part is the rotation vector
    return np.array([*(T_target[:3, 3] - T[:3, 3]), 0.5 * (R[2, 1] - R[1, 2]), 0.5 * (R[0, 2] - R[2, 0]),
                     0.5 * (R[1, 0] - R[0, 1])])


def near_inverse_kinematics(T_target: NDArray[np.float64], q_near: NDArray[np.float64],
                            steps: int = 4) -> NDArray[np.float64] | None:
    """Joint angles for a target near the pose of ``q_near`` (a servo step): a few Newton steps on the
    numerical Jacobian (about a millisecond, where ``inverse_kinematics`` takes tens); the full solve when
    they do not converge."""
    q = np.asarray(q_near, dtype=np.float64).copy()
    for _ in range(steps):
        T = forward_kinematics(q)
        err = _pose_error(T, T_target)
        if float(np.max(np.abs(err))) < 1e-9:
            return q
        J = np.empty((6, 6))
        for j in range(6):
            dq = q.copy()
            dq[j] += 1e-7
            J[:, j] = _pose_error(T, forward_kinematics(dq)) / 1e-7  # how the pose moves with joint j
        q = q + np.linalg.lstsq(J, err, rcond=None)[0]
    if float(np.max(np.abs(_pose_error(forward_kinematics(q), T_target)))) < 1e-8:
        return q
    return inverse_kinematics(T_target, q_near)


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
    slerp: Slerp | None = None
    """The orientation's interpolation, made once per move (not at every 500 Hz tick)."""
    ramp_s: float = 0.0
    """The speed profile's ramp time (``movel``'s trapezoid); 0: constant speed."""

    def fraction(self, now: float) -> tuple[float, float]:
        """(how far along, 0..1; its rate per second) at ``now``."""
        return profile_fraction(now - self.t0, self.duration_s, self.ramp_s)


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
    servo_steps: int = 0
    """servoL poses received (host-side conveyor tracking streams them)."""

    def __post_init__(self) -> None:
        self.T = forward_kinematics(self.q)

    @property
    def powered(self) -> bool:
        return self.robot_mode in (ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE, 6, ROBOT_MODE_RUNNING)

    @property
    def ready(self) -> bool:
        """Running and in normal safety: the control script may run."""
        return self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_NORMAL

    def joint_speeds(self, now: float) -> tuple[float, ...]:
        m = self.motion
        if m is None or m.duration_s <= 0:
            return (0.0,) * 6
        rate = m.fraction(now)[1]
        return tuple(float(v) for v in (m.q_end - m.q_start) * rate)

    def tcp_speed(self, now: float) -> tuple[float, ...]:
        m = self.motion
        if m is None or m.duration_s <= 0:
            return (0.0,) * 6
        v = (m.T_end[:3, 3] - m.T_start[:3, 3]) * m.fraction(now)[1]
        return (float(v[0]), float(v[1]), float(v[2]), 0.0, 0.0, 0.0)

    def halt(self) -> None:
        """Stop where the arm is (stopL / stopJ / protective stop): a waiting command gets no "done"."""
        self.motion = None

    def protective_stop(self) -> None:
        self.halt()
        self.safety_mode = SAFETY_PROTECTIVE_STOP

    def start_linear(self, pose: NDArray[np.float64], speed_m_s: float, now: float, waiting: bool,
                     duration_s: float | None = None, accel_m_s2: float = math.inf) -> bool:
        """Start ``moveL`` to a UR pose vector at ``speed_m_s`` with ``accel_m_s2`` (inf: no ramps; the control
        script always passes ``ur_rtde``'s) (or a servo step: ``duration_s`` given, the speed ignored); False when
        the target is invalid or unreachable."""
        if not (np.all(np.isfinite(pose)) and math.isfinite(speed_m_s) and speed_m_s > 0):
            return False
        T_end = pose_to_T(pose)
        q_end = inverse_kinematics(T_end, self.q) if duration_s is None else near_inverse_kinematics(T_end, self.q)
        if q_end is None:
            return False
        dist = float(np.linalg.norm(T_end[:3, 3] - self.T[:3, 3]))
        angle = float(np.linalg.norm((Rotation.from_matrix(self.T[:3, :3]).inv()
                                      * Rotation.from_matrix(T_end[:3, :3])).as_rotvec()))
        ramp = 0.0
        if duration_s is None:
            if not accel_m_s2 > 0:  # NaN too
                return False
            duration, ramp = movel_profile(dist, angle, speed_m_s * self.speed_slider, accel_m_s2)
            self.last_move = {"kind": "moveL", "pose": pose.tolist(), "speed": speed_m_s, "acceleration": accel_m_s2}
        else:
            duration = duration_s
            self.servo_steps += 1
        self.motion = Motion("linear", now, duration, self.q.copy(), q_end, self.T.copy(), T_end, waiting,
                             ramp_s=ramp)
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
        s = m.fraction(now)[0]
        self.q = m.q_start + s * (m.q_end - m.q_start)
        if m.kind == "linear":
            T = np.eye(4)
            T[:3, 3] = m.T_start[:3, 3] + s * (m.T_end[:3, 3] - m.T_start[:3, 3])
            if m.slerp is None:
                m.slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([m.T_start[:3, :3], m.T_end[:3, :3]])))
            T[:3, :3] = m.slerp([s]).as_matrix()[0]
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
