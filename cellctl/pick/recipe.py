"""A pick recipe: which part models to find, how to search, and how the gripper takes the part.

Stored versioned in the store under a PLC recipe number. Lengths are millimetres (``*_mm``),
angles degrees (``*_deg``) or radians (``*_rad``), speeds m/s.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from cellctl.pick.model import PartModel


class PickError(ValueError):
    """The pick cannot be done as asked (no calibration, bad recipe, image of the wrong size...)."""


class SearchSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min_score: float = Field(0.6, gt=0, le=1)
    max_count: int = Field(5, ge=1, le=100)
    angle_start_deg: float = -180.0
    angle_extent_deg: float = Field(360.0, gt=0, le=360)
    roi: tuple[float, float, float, float] | None = None
    timeout_s: float | None = Field(1.0, gt=0, le=60)


class Recipe(BaseModel):
    """What to pick and how (stored versioned in the store under a PLC recipe number)."""

    model_config = ConfigDict(extra="forbid")
    name: str
    models: list[dict[str, Any]] = Field(min_length=1, description="part models (cellctl pick teach output)")
    camera_id: str | None = None
    robot_id: str | None = None
    calibration: Literal["auto", "handeye", "npoint"] = "auto"
    plane_z_mm: float | None = Field(None, description="height of the parts' top face in the base frame, mm")
    grasp_offset_mm: tuple[float, float] = (0.0, 0.0)
    """Grasp point from the part's reference point, in the part's frame (x along its taught x), mm."""
    grasp_z_mm: float = 0.0
    """Tool z above the working plane at the grasp, mm."""
    approach_height_mm: float = Field(50.0, ge=0)
    grasp_yaw_deg: float = 0.0
    gripper_symmetry_deg: float = Field(180.0, gt=0, le=360)
    tool_rotvec_rad: tuple[float, float, float] = (math.pi, 0.0, 0.0)
    """Tool orientation at gripper yaw 0 (default: pointing down, tool x along base x)."""
    speed_m_s: float = Field(0.1, gt=0, le=2)
    search: SearchSettings = SearchSettings()

    def part_models(self) -> list[PartModel]:
        return [PartModel.from_dict(m, f"recipe {self.name} model {k}") for k, m in enumerate(self.models)]
