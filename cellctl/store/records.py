"""What the store returns: frozen dataclasses with JSON payloads already parsed.

Times are seconds since the epoch (UTC). A ``robot_id`` of ``None`` means a camera-only record.
The dicts inside a record are fresh copies parsed from the stored JSON text: changing them never
changes the store.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

CalibrationKind = Literal["camera", "handeye", "npoint", "conveyor"]
CALIBRATION_KINDS: tuple[CalibrationKind, ...] = ("camera", "handeye", "npoint", "conveyor")
"""``conveyor``: a belt in a robot's base frame (``conveyor-calibrate``), keyed by the conveyor's id in place of
a camera's."""


@dataclass(frozen=True)
class CalibrationSummary:
    """One stored calibration version without its (possibly large) result and inputs."""

    id: int
    cell_id: str
    kind: CalibrationKind
    camera_id: str
    robot_id: str | None
    version: int
    """1, 2, ... per (cell_id, kind, camera_id, robot_id), in the order they were saved."""
    tool_version: str
    """``cellctl.__version__`` of the process that saved it."""
    creator: str
    note: str
    created_s: float
    active: bool
    """Whether this version was the active one when it was read."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class CalibrationRecord(CalibrationSummary):
    """One stored calibration version, complete: the result and the inputs it was computed from."""

    result: dict[str, Any]
    inputs: dict[str, Any]
    """What the result was computed from: observations, robot poses, settings."""
    sha256: str
    """Checksum of the stored result and inputs text, verified on every read."""

    def summary(self) -> CalibrationSummary:
        return CalibrationSummary(**{k: getattr(self, k) for k in CalibrationSummary.__dataclass_fields__})


@dataclass(frozen=True)
class Recipe:
    """One version of a recipe (the PLC's recipe number → what to pick and how)."""

    recipe_id: int
    version: int
    name: str
    data: dict[str, Any]
    creator: str
    created_s: float
    cell_id: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class AuditEntry:
    """One logged act: who did what to which target, with what result."""

    id: int
    cell_id: str
    at_s: float
    who: str
    action: str
    target: str
    detail: dict[str, Any]
    result: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
