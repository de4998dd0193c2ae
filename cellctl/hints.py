"""A library error's hint in a front end's words: the library names what is wrong and which of its
inputs are at fault; the command line and the REST API each name those inputs their own way
(``--plane-z-mm`` on the command line, ``plane_z_mm`` in a ``POST /map`` body). Library messages name
no command-line flag (``tests/test_error_roots.py`` checks it); the flags are added here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from calibration.measure import MappingError

if TYPE_CHECKING:  # annotations only: the CLI's start-up does not load the solvers and the report for them
    from calibration.handeye import HandEyeError
    from calibration.report import TargetPrintError


def mapping_message(exc: MappingError, names: Mapping[str, str]) -> str:
    """``exc``'s message with what to do about its inputs, each called by its front end's ``names``
    (an input missing from ``names`` keeps the library's name)."""
    if not exc.inputs:
        return str(exc)
    said = " and ".join(names.get(i, i) for i in exc.inputs)
    if exc.need == "give":
        return f"{exc}: give {said}"
    if exc.need == "leave out":
        return f"{exc}; leave {said} out"
    return f"{exc}; check {said}"


CLI = "cli"
ROUTINE = "routine"
"""The front ends that word a hand-eye error's way out: the command line, a capture routine."""

_HANDEYE_WAYS: dict[tuple[str, str], str] = {
    ("dof4", CLI): ("For a SCARA / top-down-only cell, use `cellctl calib handeye --dof 4 --target-z-mm Z` "
                    "(Z: the target origin's height, base frame, mm)."),
    ("dof6", CLI): "Calibrate them with the 6-DOF solver: leave out --dof 4 and --target-z-mm.",
    ("dof4", ROUTINE): ("For a SCARA / top-down-only cell, run handeye-capture with dof 4 and target_z_mm (the plate "
                        "origin's height in the robot base frame, mm)."),
    ("dof6", ROUTINE): "Run handeye-capture with dof 6 (the robot turns the tool freely).",
}


def handeye_message(exc: HandEyeError, front: str) -> str:
    """``exc``'s message with its way out (``HandEyeError.alternative``: ``"dof4"``, ``"dof6"``) in the
    words of ``front`` (:data:`CLI` or :data:`ROUTINE`); without an alternative, the message alone."""
    way = _HANDEYE_WAYS.get((exc.alternative, front))
    return f"{str(exc).rstrip('. ')}. {way}" if way else str(exc)


def target_print_message(exc: TargetPrintError, names: Mapping[str, str]) -> str:
    """``exc``'s message with the inputs at fault called by the front end's ``names``
    (the CLI: ``{"dpi": "--dpi"}``)."""
    if not exc.inputs:
        return str(exc)
    return f"{exc}; check {' and '.join(names.get(i, i) for i in exc.inputs)}"
