"""Plausibility checks of numbers at the edge (REST and CLI): poses, pixels and mapped points.

Pydantic refuses NaN/Infinity (``allow_inf_nan=False``) and bounds single fields; these checks
cover what one field bound cannot: a UR pose whose translation is in millimetres instead of
metres, a pixel outside the camera's image, a mapped point that is not finite or lies beyond any
work cell. Each returns the problem as a message naming the field (None when fine).
Units: UR poses ``[x, y, z, rx, ry, rz]`` in metres and radians; points in millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

MAX_COORD_MM = 1e5
"""Nothing in a work cell is 100 m from the robot base: larger coordinates are input errors."""
MAX_ROTVEC_RAD = 2 * math.pi
"""A rotation vector's norm is its angle; beyond one full turn it is not a pose anyone measured."""
MAX_OUTSIDE_ENVELOPE_MM = 1000.0
"""A given robot pose may lie this far outside the configured envelope (the pendant can jog there)."""


def pose_ur_problem(pose: Sequence[float], field: str) -> str | None:
    """Magnitude check of a UR pose (metres, radians)."""
    if len(pose) != 6:
        return f"{field} has 6 numbers [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad], got {len(pose)}"
    for i, v in enumerate(pose):
        if not math.isfinite(v):
            return f"{field}[{i}] = {v} is not a finite number"
    for i, v in enumerate(pose[:3]):
        if abs(v) * 1e3 > MAX_COORD_MM:
            return (f"{field}[{i}] = {v:g} m is beyond {MAX_COORD_MM / 1e3:g} m from the robot base; "
                    f"{field} is in metres and radians (UR form)")
    norm = math.hypot(*pose[3:])
    if norm > MAX_ROTVEC_RAD:
        return (f"{field}: the rotation vector [{pose[3]:g}, {pose[4]:g}, {pose[5]:g}] turns by {norm:g} rad, more "
                f"than one full turn ({MAX_ROTVEC_RAD:.4f} rad); give the UR rotation vector in radians")
    return None


def pose_envelope_problem(pose: Sequence[float], envelope_mm: Sequence[tuple[float, float]], robot_id: str,
                          field: str) -> str | None:
    """A given robot pose far outside the robot's envelope (x, y, z boxes in mm) is a unit or typing error."""
    p_mm = [v * 1e3 for v in pose[:3]]
    outside_mm = max(max(lo - v, v - hi, 0.0) for v, (lo, hi) in zip(p_mm, envelope_mm, strict=True))
    if outside_mm <= MAX_OUTSIDE_ENVELOPE_MM:
        return None
    msg = (f"{field}: the tool position ({p_mm[0]:.0f}, {p_mm[1]:.0f}, {p_mm[2]:.0f}) mm is {outside_mm / 1e3:.1f} m "
           f"outside robot {robot_id}'s envelope (x {_box(envelope_mm[0])}, y {_box(envelope_mm[1])}, "
           f"z {_box(envelope_mm[2])} mm); {field} is in metres and radians (UR form)")
    in_mm = all(lo - MAX_OUTSIDE_ENVELOPE_MM <= v * 1e-3 <= hi + MAX_OUTSIDE_ENVELOPE_MM
                for v, (lo, hi) in zip(p_mm, envelope_mm, strict=True))
    if in_mm:
        msg += f": these look like millimetres, send [{pose[0] / 1e3:g}, {pose[1] / 1e3:g}, {pose[2] / 1e3:g}, ...]"
    return msg


def _box(lo_hi: tuple[float, float]) -> str:
    return f"[{lo_hi[0]:g}, {lo_hi[1]:g}]"


def pixel_problem(u_px: float, v_px: float, size: tuple[int, int] | None, camera_id: str,
                  names: tuple[str, str] = ("u_px", "v_px")) -> str | None:
    """A pixel outside the camera's image ((0, 0) is the centre of the top-left pixel) cannot be mapped.

    ``names``: what the caller's front end calls the two coordinates (the REST body's by default)."""
    if size is None:
        return None
    w, h = size
    for name, value, n in ((names[0], u_px, w), (names[1], v_px, h)):
        if not -0.5 <= value <= n - 0.5:
            return (f"{name} = {value:g} is outside camera {camera_id}'s {w}x{h} image (-0.5 .. {n - 0.5:g}; "
                    "(0, 0) is the centre of the top-left pixel)")
    return None


def point_problem(xyz_mm: Sequence[float], sigma_mm: Sequence[float], z_may_be_unknown: bool) -> str | None:
    """A mapped point that is not finite, or beyond any work cell, is a failure, never an answer."""
    names = ("x_mm", "y_mm", "z_mm")
    for name, v in zip(names, xyz_mm, strict=True):
        if name == "z_mm" and z_may_be_unknown and math.isnan(v):
            continue
        if not math.isfinite(v) or abs(v) > MAX_COORD_MM:
            return (f"the pixel maps to {name} = {v:g}, beyond {MAX_COORD_MM:g} mm: the ray meets the working "
                    "plane almost edge-on or the inputs (u_px, v_px, plane_z_mm, robot_pose_ur) are not of this cell")
    for s in sigma_mm:
        if not math.isfinite(s) or s > MAX_COORD_MM:
            return f"the mapped point's uncertainty ({s:g} mm) is not finite: the inputs cannot be mapped reliably"
    return None


def transform_problem(T: Sequence[Sequence[float]], field: str) -> str | None:
    """Magnitude check of a 4x4 ``T`` (metres): finite, a rotation's entries within +-1, a sane translation."""
    if len(T) != 4 or any(len(row) != 4 for row in T):
        return f"{field} must be a 4x4 matrix (rows of 4 numbers)"
    for r, row in enumerate(T):
        for c, v in enumerate(row):
            if not math.isfinite(v):
                return f"{field}[{r}][{c}] = {v} is not a finite number"
            if r < 3 and c < 3 and abs(v) > 1.0 + 1e-6:
                return f"{field}[{r}][{c}] = {v:g}: a rotation matrix's entries lie within [-1, 1]"
            if r < 3 and c == 3 and abs(v) * 1e3 > MAX_COORD_MM:
                return (f"{field}[{r}][3] = {v:g} m is beyond {MAX_COORD_MM / 1e3:g} m from the robot base; "
                        f"{field} is in metres")
    if [float(x) for x in T[3]] != [0.0, 0.0, 0.0, 1.0]:
        return f"{field}'s last row must be [0, 0, 0, 1], got {list(T[3])}"
    return None
