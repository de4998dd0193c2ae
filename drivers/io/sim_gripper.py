"""Simulated 2-finger gripper (``kind: sim_gripper``): the gripper of the virtual production cell.

It acts on the scene's parts (``drivers.sim.production``): closing holds the part it closes on
when the gripper's centre (the robot's TCP, from the tool's *true* pose) is within the scene's
grip tolerance of the part, else it closes empty; the held part moves with the tool; opening lets
it go where it is (it lands on the surface below). The scene's gripper faults apply (a seeded
failure probability, a slip at an acceleration).

It speaks the Robotiq 2F API of ``drivers.io.robotiq_gripper`` (``open_gripper``,
``close_gripper``, ``move``, ``status`` with ``object_detected`` and ``position`` 0 open .. 255
closed, plus ``width_mm``), so a recipe drives either the same way, and the ``DigitalIO``
contract: output 0 closes (True) / opens (False), input 0 reads "object detected".
Closing and opening take the scene's ``actuation_s`` times ``time_scale``.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from drivers.base import DeviceOperationError, DeviceUnavailable, DigitalIOBase
from drivers.health import DeviceHealth
from drivers.sim.production import ProductionParts
from drivers.sim.world import SimWorld, world_for


class SimGripperSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene: str | None = None
    """Scene file path (must be the sim robot's and camera's); empty for the built-in scene."""
    seed: int | None = Field(None, ge=0)
    time_scale: float = Field(1.0, ge=0, le=10)
    """Closing and opening take the scene's ``actuation_s`` times this (0: at once)."""


class SimGripper(DigitalIOBase):
    """A gripper that exists only in the virtual production cell."""

    Settings = SimGripperSettings

    def __init__(self, io_id: str, settings: SimGripperSettings | dict[str, Any]) -> None:
        super().__init__(io_id)
        self.config = (settings if isinstance(settings, SimGripperSettings)
                       else SimGripperSettings.model_validate(settings))
        self._world: SimWorld | None = None
        self._lock = threading.Lock()
        self.last_reason = ""
        """Why the last close held nothing (the sim's own explanation, for tests and logs)."""

    def open(self) -> None:
        world = world_for(self.config.scene, self.config.seed)
        if world.production is None:
            raise DeviceUnavailable(f"io {self.io_id}: the scene {world.source!r} has no production section, so "
                                    "there is nothing for a sim gripper to grip; use the production scene")
        self._world = world

    def close(self) -> None:
        self._world = None

    def _parts(self) -> tuple[SimWorld, ProductionParts]:
        world = self._world
        if world is None or world.production is None:
            raise DeviceUnavailable(f"io {self.io_id}: not open; open() it first")
        return world, world.production

    def _actuate(self) -> None:
        _, parts = self._parts()
        delay = parts.spec.gripper.actuation_s * self.config.time_scale
        if delay > 0:
            time.sleep(delay)

    # -- the Robotiq-style API ------------------------------------------------------------------------
    def move(self, position: int, speed_percent: float | None = None, force_percent: float | None = None,
             wait: bool = True) -> dict[str, Any]:
        """Close (position > 127) or open (<= 127) the fingers; the final status."""
        if not 0 <= position <= 255:
            raise DeviceOperationError(f"io {self.io_id}: position {position} is not in 0..255")
        world, parts = self._parts()
        with self._lock:
            self._actuate()
            if position > 127:
                outcome = parts.close(world.T_base_tool_true)
                self.last_reason = outcome.reason
            else:
                parts.open(world.T_base_tool_true)
                self.last_reason = ""
            world.keep()  # a kept world (a restart finds the part where the gripper left it)
        return self.status()

    def open_gripper(self, **kw: Any) -> dict[str, Any]:
        return self.move(0, **kw)

    def close_gripper(self, **kw: Any) -> dict[str, Any]:
        return self.move(255, **kw)

    def activate(self) -> None:
        """Nothing to calibrate: the sim gripper is active once open."""
        self._parts()

    def status(self) -> dict[str, Any]:
        """As the Robotiq adapter's: activated, object_detected, position (0..255), plus width_mm."""
        _, parts = self._parts()
        width = parts.width_mm()
        stroke = parts.spec.gripper.open_width_mm
        held = parts.held()
        return {"activated": True, "moving": False, "object_detected": held is not None,
                "at_position": held is None, "fault": 0, "fault_text": "",
                "position_request": 255 if parts.closed else 0,
                "position": round(255 * (1.0 - width / stroke)), "width_mm": width,
                "closed": parts.closed, "holding": None if held is None else held.id}

    # -- DigitalIO contract -------------------------------------------------------------------------
    def write_output(self, channel: int, value: bool) -> None:
        if channel != 0:
            raise DeviceOperationError(f"io {self.io_id}: the gripper has one output (0: close/open), not {channel}")
        self.move(255 if value else 0)

    def read_input(self, channel: int) -> bool:
        if channel != 0:
            raise DeviceOperationError(f"io {self.io_id}: the gripper has one input (0: object detected), "
                                       f"not {channel}")
        return bool(self.status()["object_detected"])

    def health(self) -> DeviceHealth:
        return DeviceHealth(available=self._world is not None, reason="" if self._world else "not open")
