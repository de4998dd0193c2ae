"""Simulated conveyor (``kind: sim_conveyor``): the belt of a conveyor scene (``drivers.sim.conveyor``).

Its settings set the belt's speed (0-300 mm/s, and a slow variation) when it opens, and its pick
window; the encoder is the scene's (``ticks_per_m`` there, 10000 in the built-in conveyor cell).
The faults a test plays (``belt``: ``simulate_encoder_stop``, ``simulate_count_jump``, ``set_speed(0)``)
are the world's, so the camera's latched counts and the robot's tracking see them too.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from drivers.base import DeviceUnavailable
from drivers.conveyor.base import ConveyorBase
from drivers.sim.conveyor import MAX_SPEED_MM_S, SimBelt
from drivers.sim.world import world_for


class SimConveyorSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    scene: str | None = None
    """The conveyor scene (``conveyor``: the built-in one; or a path); must be the sim camera's and robot's."""
    seed: int | None = Field(None, ge=0)
    speed_mm_s: float | None = Field(None, ge=0, le=MAX_SPEED_MM_S)
    """The belt's speed, mm/s (default: the scene's)."""
    speed_variation: float | None = Field(None, ge=0, le=0.5)
    """A slowly varying belt: the speed swings by this fraction (default: the scene's, 0)."""
    pick_window_mm: tuple[float, float] | None = None
    """Base x the robot can reach on the belt, mm (default: the scene's)."""


class SimConveyor(ConveyorBase):
    """The virtual conveyor cell's belt."""

    Settings = SimConveyorSettings

    def __init__(self, conveyor_id: str, settings: SimConveyorSettings) -> None:
        super().__init__(conveyor_id)
        self._settings = settings
        self._belt: SimBelt | None = None

    @property
    def belt(self) -> SimBelt:
        if self._belt is None:
            raise DeviceUnavailable(f"conveyor {self.conveyor_id}: not open; open() it first")
        return self._belt

    def open(self) -> None:
        world = world_for(self._settings.scene, self._settings.seed)
        if world.belt is None:
            raise DeviceUnavailable(f"conveyor {self.conveyor_id}: scene {world.scene.name!r} has no conveyor "
                                    "(use scene: conveyor)")
        s = self._settings
        if s.speed_mm_s is not None or s.speed_variation is not None:
            world.belt.configure(world.belt.speed_mm_s() if s.speed_mm_s is None else s.speed_mm_s,
                                 s.speed_variation)
        self._belt = world.belt

    def close(self) -> None:
        self._belt = None

    def ticks(self) -> int:
        return self.belt.ticks()

    def speed_mm_s(self) -> float | None:
        return self.belt.speed_mm_s()

    @property
    def pick_window_mm(self) -> tuple[float, float]:
        w = self._settings.pick_window_mm
        if w is not None:
            return (float(w[0]), float(w[1]))
        spec = world_for(self._settings.scene, self._settings.seed).scene.conveyor
        if spec is None:
            raise DeviceUnavailable(f"conveyor {self.conveyor_id}: the scene has no conveyor (use scene: conveyor)")
        return spec.pick_window_mm

    def set_speed(self, speed_mm_s: float, variation: float | None = None) -> None:
        """Set the belt's speed now (mm/s, 0-300): the virtual plant's drive."""
        self.belt.set_speed(speed_mm_s, variation)

    def settings(self) -> dict[str, Any]:
        return {"kind": "sim_conveyor", **self._settings.model_dump(mode="json")}
