"""A production run's settings, status and states (``cellctl.production.run`` runs it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from cellctl.pick.recipe import Recipe
from cellctl.production.records import Counters, CycleTimes

State = Literal["running", "pausing", "paused", "stopping", "stopped", "complete", "failed", "interrupted"]
Ended = Literal["count_reached", "area_empty", "none_pickable", "not_recognized", "stopped", "failed", "interrupted"]
Phase = Literal["starting", "to_capture", "vision", "to_pick", "closing", "lifting", "carrying", "over_slot",
                "releasing", "leaving", "between"]
"""Where a run is in its cycle: ... ``carrying`` (to above the slot, the slot claimed), ``over_slot`` (down
to it), ``releasing`` (the gripper opening), ``leaving`` (up from it, the part let go)."""


@dataclass
class RunSettings:
    recipe_id: int
    recipe_version: int
    recipe: Recipe
    robot_id: str
    camera_id: str
    count: int
    overlap: bool
    who: str


@dataclass
class RunStatus:
    run_id: int
    recipe_id: int
    robot_id: str
    state: State = "running"
    ended_because: Ended | None = None
    error: str | None = None
    stop_reason: str | None = None
    """Why a ``stopped`` run stopped (a Stop, an operator's stop, the service shutting down)."""
    counters: Counters = field(default_factory=Counters)
    times: CycleTimes = field(default_factory=CycleTimes)
