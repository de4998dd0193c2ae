"""A robot's motion limits: the workspace envelope (a box in the base frame, mm), the tool's
orientation cone, the speed limits and how long a move may take. ``RobotBase`` checks every
commanded pose and speed against them before an adapter sees it (``MotionRejected`` otherwise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.errors import MotionRejected

_I3 = np.eye(3)
_ORTHONORMAL_TOL = 1e-6 + 1e-5 * _I3
"""``np.allclose(R.T @ R, I, atol=1e-6)``'s bound per element (atol + rtol * |I|), written out: a pose check
runs for every candidate a capture plan weighs (~500 a station), and ``allclose`` costs 10x the comparison."""

@dataclass(frozen=True)
class MotionLimits:
    """The workspace envelope (a box in the base frame, mm) and the speed limits."""

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    max_linear_speed_m_s: float
    max_joint_speed_rad_s: float = math.pi / 2
    joint_limits_rad: tuple[tuple[float, float], ...] | None = None
    tool_down_cone_deg: float | None = 60.0
    """Largest angle between the tool's z axis and the base's -z ("down"); None: not checked."""
    max_move_duration_s: float = 60.0
    """A move that would take longer at the commanded speed is refused (too slow to supervise)."""
    move_deadline_slack_s: float = 5.0
    """A move may take 1.5x its nominal duration plus this (s) before it is stopped as late."""

    def check_pose(self, T_base_tool: NDArray[np.float64]) -> None:
        """Raise MotionRejected when the tool position is outside the envelope."""
        T = np.asarray(T_base_tool, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise MotionRejected("target pose must be a finite 4x4 T_base_tool matrix")
        p_mm = T[:3, 3] * 1000.0
        for axis, value, (lo, hi) in zip("xyz", p_mm, (self.x_mm, self.y_mm, self.z_mm), strict=True):
            if not lo <= value <= hi:
                raise MotionRejected(
                    f"target {axis} = {value:.1f} mm is outside the workspace envelope "
                    f"[{lo:.1f}, {hi:.1f}] mm; choose a pose inside it or widen the envelope in cell.yaml"
                )
        R = T[:3, :3]
        if not np.all(np.abs(R.T @ R - _I3) <= _ORTHONORMAL_TOL) or not np.linalg.det(R) > 0:
            raise MotionRejected("target pose's rotation is not a proper rotation matrix (orthonormal, det +1)")
        if self.tool_down_cone_deg is not None:
            # The tool's z axis in the base frame is R's third column; "down" is (0, 0, -1).
            tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, -float(R[2, 2])))))
            if tilt_deg > self.tool_down_cone_deg:
                raise MotionRejected(
                    f"target tool orientation is {tilt_deg:.1f} deg from pointing down, more than the allowed "
                    f"{self.tool_down_cone_deg:.1f} deg; give a pose with the tool pointing down or widen "
                    "tool_down_cone_deg for this robot in cell.yaml"
                )

    def check_linear_speed(self, speed_m_s: float) -> None:
        if not math.isfinite(speed_m_s) or speed_m_s <= 0 or speed_m_s > self.max_linear_speed_m_s:
            raise MotionRejected(
                f"linear speed {speed_m_s} m/s is outside (0, {self.max_linear_speed_m_s}] m/s "
                "(the configured speed limit)"
            )

    def check_duration(self, distance: float, speed: float, unit: str) -> float:
        """The nominal duration (s) of a move of ``distance`` at ``speed``; refused when too long."""
        duration_s = distance / speed
        if not math.isfinite(duration_s) or duration_s > self.max_move_duration_s:
            min_speed = distance / self.max_move_duration_s
            raise MotionRejected(
                f"at {speed:.3g} {unit}/s the move of {distance:.4g} {unit} would take {duration_s:.3g} s, more "
                f"than the {self.max_move_duration_s:.0f} s a move may take; use at least {min_speed:.3g} {unit}/s"
            )
        return duration_s

    def check_joint_speed(self, speed_rad_s: float) -> None:
        if not math.isfinite(speed_rad_s) or speed_rad_s <= 0 or speed_rad_s > self.max_joint_speed_rad_s:
            raise MotionRejected(
                f"joint speed {speed_rad_s} rad/s is outside (0, {self.max_joint_speed_rad_s}] rad/s "
                "(the configured joint speed limit)"
            )

    def check_joints(self, joints_rad: NDArray[np.float64]) -> None:
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(q)):
            raise MotionRejected("joint target contains NaN or infinity")
        if self.joint_limits_rad is None:
            return
        if len(q) != len(self.joint_limits_rad):
            raise MotionRejected(f"joint target has {len(q)} values, the robot has {len(self.joint_limits_rad)}")
        for i, (value, (lo, hi)) in enumerate(zip(q, self.joint_limits_rad, strict=True)):
            if not lo <= value <= hi:
                raise MotionRejected(f"joint {i} target {value:.4f} rad is outside [{lo:.4f}, {hi:.4f}] rad")
