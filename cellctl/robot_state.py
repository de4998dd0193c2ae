"""Robot state as JSON: the 4x4 ``T_base_tool`` (m) and the UR pose form with units in the names."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from calibration.geometry import transform_to_ur_pose
from drivers.base import RobotState


def state_to_json(robot_id: str, state: RobotState) -> dict[str, Any]:
    x, y, z, rx, ry, rz = (float(v) for v in transform_to_ur_pose(state.T_base_tool))
    return {
        "robot_id": robot_id,
        "T_base_tool": np.asarray(state.T_base_tool, dtype=float).tolist(),
        "pose_ur": {"x_m": x, "y_m": y, "z_m": z, "rx_rad": rx, "ry_rad": ry, "rz_rad": rz},
        "joints_rad": [float(v) for v in np.asarray(state.joints_rad).reshape(-1)],
        "timestamp_s": float(state.timestamp_s),
        "age_s": max(0.0, time.time() - float(state.timestamp_s)),
        "moving": bool(state.moving),
        "mode": state.mode,
    }
