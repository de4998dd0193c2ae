"""The values that cross the driver contract: a camera's ``Frame`` and a robot's ``RobotState``.

Units: ``T_base_tool`` 4x4 in metres, joints in radians, times in seconds since the Unix epoch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Frame:
    """One camera image: pixels (H, W) grey or (H, W, 3) BGR, and when it was taken."""

    pixels: NDArray[Any]
    timestamp_s: float
    """Capture time, seconds since the Unix epoch (camera clock mapped to host when available)."""
    frame_id: int = 0
    camera_id: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def meta(self) -> dict[str, Any]:
        """``metadata`` (the name docs/conveyor.md uses: ``Frame.meta["encoder_ticks"]``, a belt's count
        latched at the exposure)."""
        return self.metadata

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (int(self.pixels.shape[1]), int(self.pixels.shape[0]))


@dataclass(frozen=True)
class RobotState:
    """The robot's state: ``T_base_tool`` (4x4, metres), joints (radians), time, modes."""

    T_base_tool: NDArray[np.float64]
    joints_rad: NDArray[np.float64]
    timestamp_s: float
    """When the state was sampled, seconds since the Unix epoch (host clock)."""
    moving: bool = False
    mode: str = "running"
    metadata: dict[str, Any] = field(default_factory=dict)

    def age_s(self, now_s: float | None = None) -> float:
        return (time.time() if now_s is None else now_s) - self.timestamp_s
