"""``drift:`` in cell.yaml: what a fixed camera checks itself against, and how often (docs/drift.md).

The fiducials are either marks (``marks``: 3 or more points with their base-frame positions, bright
disks of ``mark_diameter_mm`` on a darker table) or a target fixed to the table (``target``: a name
in ``targets``, at ``T_base_target_ur``, UR form: metres and a rotation vector in radians).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, model_validator

from cellctl.strict_types import ClosedModel


class FiducialsConfig(ClosedModel):
    marks_mm: list[tuple[float, float, float]] | None = None
    """Marks' centres in the base frame, ``[x_mm, y_mm, z_mm]`` each (3 or more)."""
    mark_diameter_mm: float = Field(4.0, gt=0, le=100)
    target: str | None = None
    """A target of ``targets`` fixed to the table (instead of marks)."""
    T_base_target_ur: tuple[float, float, float, float, float, float] | None = None
    """The fixed target's pose in the base frame (UR form: x_m, y_m, z_m, rx_rad, ry_rad, rz_rad)."""

    @model_validator(mode="after")
    def _one_kind(self) -> FiducialsConfig:
        if (self.marks_mm is None) == (self.target is None):
            raise ValueError("drift.fiducials needs either marks_mm (3 or more [x_mm, y_mm, z_mm] in the base "
                             "frame) or target (a name in targets) with T_base_target_ur, not both")
        if self.marks_mm is not None and len(self.marks_mm) < 3:
            raise ValueError(f"drift.fiducials.marks_mm has {len(self.marks_mm)} marks; a drift check needs 3 or "
                             "more (4 or more to re-solve the camera)")
        if self.target is not None and self.T_base_target_ur is None:
            raise ValueError("drift.fiducials.target needs T_base_target_ur: where the target lies in the base frame")
        return self


class DriftConfig(ClosedModel):
    """Drift checks of one camera against its active hand-eye calibration (fixed, or on the arm from a station)."""

    camera: str | None = None
    """The camera checked; default ``calibration.camera``."""
    robot: str | None = None
    """The robot of its hand-eye; default ``calibration.robot``."""
    fiducials: FiducialsConfig
    every_cycles: int = Field(10, ge=0, le=1_000_000)
    """A check on every this many production pictures (0: none in production)."""
    every_s: float = Field(60.0, ge=0, le=86400)
    """A check this often while no production run uses the camera (0: none when idle)."""
    baseline_checks: int = Field(20, ge=2, le=10_000)
    """Checks after the active calibration changed that set the chart's limits."""
    min_sigma_mm: float = Field(0.02, ge=0, le=10)
    """A floor under the chart's sigma, mm: drift far below what a pick notices raises no alarm."""
    window_px: float = Field(40.0, gt=2, le=500)
    """Half-size of the window a mark is looked for in around where the calibration puts it, pixels."""
    pause_on_alarm: bool = False
    """Pause a production run (after the current cycle) when a check raises an alarm."""
    resolve_max_rms_px: float = Field(0.5, gt=0, le=100)
    """A re-solve whose fiducials fit worse than this (RMS, pixels) gets a verdict that is not ok."""

    def ids(self, calibration: Any) -> tuple[str, str]:
        """(camera_id, robot_id) with the calibration defaults filled in."""
        return (self.camera or calibration.camera, self.robot or calibration.robot)
