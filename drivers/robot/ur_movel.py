"""How long a UR controller's ``movel`` takes: its trapezoidal speed profiles (the UR emulator's motion and the
``ur_rtde`` adapter's estimate, ``URRTDERobot.linear_move_s``).

What a UR controller does with ``movel(pose, a, v)`` (URScript manual, module motion: ``a`` tool acceleration
[m/s^2], ``v`` tool speed [m/s]; the move accelerates to and cruises at ``v``, then decelerates: PolyScope's
speed profile of a move, acceleration / cruise / deceleration): the position and the orientation each get a
trapezoidal profile; the orientation's speed and acceleration are derived from ``v`` and ``a`` (4 x ``v`` rad/s
and 4 x ``a`` rad/s^2: Universal Robots' forum, "MoveL: Tool Angular Speed",
forum.universal-robots.com/t/movel-tool-angular-speed/15912, the controller's behaviour as measured there);
the longer profile sets the move's time and the other is slowed to it. The orientation's speed is further
held to the arm's joint speed (a UR5e's joints turn at most 180 deg/s, its technical specification: a turn of
the tool about its axis is a turn of wrist 3). The speed slider scales ``v`` (and so the turn).

Units: metres, radians, seconds.
"""

from __future__ import annotations

import math

TURN_PER_SPEED = 4.0
"""The orientation's speed (rad/s) per m/s of ``v``, and its acceleration (rad/s^2) per m/s^2 of ``a``."""
UR5E_JOINT_SPEED_RAD_S = math.pi
"""A UR5e's joint speed limit (180 deg/s, every joint)."""


def trapezoid(length: float, speed: float, accel: float) -> tuple[float, float]:
    """(duration, ramp time) of a trapezoidal profile over ``length`` at most ``speed`` with ``accel`` ramps (a
    triangle when the length is too short to reach ``speed``); (0, 0) for no length."""
    if length <= 0.0:
        return 0.0, 0.0
    if speed <= 0.0 or accel <= 0.0:
        return math.inf, 0.0
    if length >= speed * speed / accel:
        return length / speed + speed / accel, speed / accel
    ramp = math.sqrt(length / accel)
    return 2.0 * ramp, ramp


def movel_profile(distance_m: float, angle_rad: float, speed_m_s: float, accel_m_s2: float,
                  max_turn_rad_s: float = UR5E_JOINT_SPEED_RAD_S) -> tuple[float, float]:
    """(duration, ramp time) of ``movel`` over ``distance_m`` and a turn of ``angle_rad`` at ``v = speed_m_s``,
    ``a = accel_m_s2``: the longer of the position's and the orientation's profiles (module docstring)."""
    lin = trapezoid(distance_m, speed_m_s, accel_m_s2)
    rot = trapezoid(angle_rad, min(TURN_PER_SPEED * speed_m_s, max_turn_rad_s), TURN_PER_SPEED * accel_m_s2)
    return max(lin, rot)


def profile_fraction(t: float, duration: float, ramp: float) -> tuple[float, float]:
    """(fraction of the way, its rate per second) at ``t`` s into a trapezoidal profile of ``duration`` with
    ``ramp`` s ramps (``ramp`` 0: constant speed)."""
    if duration <= 0.0 or t >= duration:
        return 1.0, 0.0
    t = max(0.0, t)
    ramp = min(ramp, duration / 2.0)
    if ramp <= 0.0:
        return t / duration, 1.0 / duration
    peak = 1.0 / (duration - ramp)
    if t < ramp:
        return 0.5 * peak * t * t / ramp, peak * t / ramp
    if t <= duration - ramp:
        return 0.5 * peak * ramp + peak * (t - ramp), peak
    left = duration - t
    return 1.0 - 0.5 * peak * left * left / ramp, peak * left / ramp
