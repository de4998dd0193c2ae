"""Simulated robot (``kind: sim``): moves the virtual cell's tool to commanded poses.

The motion checks live in ``RobotBase``; this adapter only places the tool. The reported pose
carries the scene's repeatability noise (drawn once per move), the true pose drives the camera.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from drivers.base import DeviceUnavailable, MotionLimits, RobotBase, RobotState
from drivers.sim.world import SimWorld, world_for


class SimRobotSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene: str | None = None
    """Scene file path; empty for the built-in virtual cell (must match the sim camera's)."""
    seed: int | None = Field(None, ge=0)


class SimRobot(RobotBase):
    """A robot arm that exists only in the virtual cell."""

    Settings = SimRobotSettings

    def __init__(self, robot_id: str, settings: SimRobotSettings, limits: MotionLimits) -> None:
        super().__init__(robot_id, limits)
        self._settings = settings
        self._world: SimWorld | None = None
        self._stop = threading.Event()
        self._moving = False

    @property
    def world(self) -> SimWorld:
        if self._world is None:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected; connect() it first")
        return self._world

    def connect(self) -> None:
        self._world = world_for(self._settings.scene, self._settings.seed)

    def close(self) -> None:
        self._world = None

    def state(self) -> RobotState:
        world = self.world
        return RobotState(
            T_base_tool=world.T_base_tool_reported(),
            joints_rad=np.zeros(6),
            timestamp_s=time.time(),
            moving=self._moving,
            mode="running",
            metadata={"simulated": True},
        )

    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        world = self.world
        self._stop.clear()
        scale = world.scene.robot.motion_time_scale
        if scale > 0:
            distance = float(np.linalg.norm(T_base_tool[:3, 3] - world.T_base_tool_true[:3, 3]))
            self._moving = True
            try:
                if self._stop.wait(distance / speed_m_s * scale):
                    return  # stopped: the tool stays where it was
            finally:
                self._moving = False
        world.place_tool(T_base_tool)

    def stop(self) -> None:
        self._stop.set()
