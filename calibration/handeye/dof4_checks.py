"""Checks and statistics of 4-DOF hand-eye data (robots that turn the tool only about base z).

``G_i = T_base_tool``; a pose set is 4-DOF when every orientation is ``Rz(θ_i) R_0`` with ``R_0``
the first pose's: the tool's z axis keeps its direction in the base frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.geometry import invert, rotation_angle
from calibration.handeye.model import HandEyeError

Mat4 = NDArray[np.float64]


def tool_tilts_deg(G: Sequence[Mat4], G_ref: Mat4) -> NDArray[np.float64]:
    """Per pose: the angle (deg) between its tool z axis and the reference pose's, in the base frame."""
    z0 = G_ref[:3, 2]
    return np.array([np.degrees(np.arccos(np.clip(g[:3, 2] @ z0, -1.0, 1.0))) for g in G])


def is_dof4(G: Sequence[Mat4], max_tilt_deg: float = 1.0) -> bool:
    """True when every pose keeps the first pose's tool z direction within ``max_tilt_deg``."""
    return len(G) > 0 and bool(np.all(tool_tilts_deg(G, G[0]) <= max_tilt_deg))


def check_dof4_motion(G: Sequence[Mat4], G_ref: Mat4, max_tilt_deg: float) -> dict[str, Any]:
    """Refuse poses that are not 4-DOF or do not turn; return the motion's summary."""
    tilts = tool_tilts_deg(G, G_ref)
    worst = int(np.argmax(tilts))
    if tilts[worst] > max_tilt_deg:
        raise HandEyeError(
            f"the 4-DOF solver needs poses that differ only by a turn about the base z axis (SCARA, top-down), but "
            f"station {worst}'s tool z axis is tilted {tilts[worst]:.2f} deg against the first pose's (limit "
            f"{max_tilt_deg:g} deg): these poses need the 6-DOF solver", alternative="dof6")
    R0 = G_ref[:3, :3]
    theta = np.degrees([np.arctan2((g[:3, :3] @ R0.T)[1, 0], (g[:3, :3] @ R0.T)[0, 0]) for g in G])
    span = float(np.ptp(theta)) if len(theta) else 0.0
    xy = np.array([g[:2, 3] for g in G])
    spread_mm = float(1e3 * np.max(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))
    if span < 10.0:
        raise HandEyeError(f"the tool turns only {span:.1f} deg about z over all stations; the camera's turn "
                           "about z cannot be determined: turn the tool by 20-90 deg between stations")
    return {"turn_span_deg": span, "max_tool_tilt_deg": float(tilts.max()), "xy_spread_mm": spread_mm,
            "tool_z_axis_base": R0[:, 2].tolist()}


def pair_residuals(setup: str, G: Sequence[Mat4], C: Sequence[Mat4], X: Mat4
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per station pair: rotation (deg) and translation (mm) of the AX = XB mismatch with ``X``."""
    H = [g if setup == "eye-in-hand" else invert(g) for g in G]
    rot, tr = [], []
    for i in range(len(H)):
        for j in range(i + 1, len(H)):
            A = invert(H[j]) @ H[i]
            B = C[j] @ invert(C[i])
            E = invert(A @ X) @ X @ B
            rot.append(np.degrees(rotation_angle(E[:3, :3])))
            tr.append(1e3 * np.linalg.norm((A @ X)[:3, 3] - (X @ B)[:3, 3]))
    return np.array(rot), np.array(tr)
