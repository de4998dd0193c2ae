"""Calibration routines run as jobs: name -> ``run(services, ctx) -> result``.

Every routine leaves the robot stopped when it fails or is cancelled (an end hook), and stores
nothing unless it completes; a new calibration is stored but not activated. Every shot a routine
measures with is taken while it owns the robot's motion (``common.robot_still``): no other caller
moves the robot during it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final

from cellctl.jobs import JobContext
from cellctl.services import Services

Routine = Callable[[Services, JobContext], dict[str, Any]]

__all__ = ["ENGINEER_ONLY", "HOLDS_ROBOT", "MOVES_ROBOT", "NEEDS_CONVEYOR", "ROUTINE_MODULES", "Routine", "routine"]
"""Starting one (the rules REST and the PLC share) is ``cellctl.routines.start.start_routine``: it imports
this package, so it is not re-exported here."""

ROUTINE_MODULES: Final[dict[str, str]] = {
    "intrinsics-capture": "cellctl.routines.intrinsics_capture",
    "handeye-capture": "cellctl.routines.handeye_capture",
    "jog-to-mark": "cellctl.routines.jog_to_mark",
    "verify": "cellctl.routines.verify",
    "conveyor-calibrate": "cellctl.routines.conveyor_calibrate",
}
MOVES_ROBOT: Final[frozenset[str]] = frozenset({"intrinsics-capture", "handeye-capture"})
ENGINEER_ONLY: Final[frozenset[str]] = frozenset({"conveyor-calibrate"})
NEEDS_CONVEYOR: Final[frozenset[str]] = frozenset({"conveyor-calibrate"})
"""Routines listed (``GET /routines``) only in a cell whose config names a conveyor."""
"""Routines that need the engineer role without moving the robot (they calibrate the cell against a moving belt)."""
HOLDS_ROBOT: Final[frozenset[str]] = frozenset({"verify"})
"""Routines that measure with the robot standing still: they hold it still for their whole run
without moving it (the operator role is enough); refused (409 robot_busy) while another caller
moves it; a latched robot may be held (it stands still)."""


def routine(name: str) -> Any:
    """The routine module (with ``Params`` and ``run``) registered under ``name``."""
    import importlib

    try:
        return importlib.import_module(ROUTINE_MODULES[name])
    except KeyError:
        raise KeyError(f"no routine {name!r}; routines: {', '.join(sorted(ROUTINE_MODULES))}") from None
