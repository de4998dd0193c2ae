"""A pick recipe: which part models to find, how to search, and how the gripper takes the part.

Stored versioned in the store under a PLC recipe number. Lengths are millimetres (``*_mm``),
angles degrees (``*_deg``) or radians (``*_rad``), speeds m/s; the capture pose is in UR form
(metres and a rotation vector in radians). A part's yaw in a pick answer is relative to the teach
image: 0 means the part lies as it did when taught, positive counter-clockwise on screen.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_serializer, field_validator

from cellctl.errors import CellctlError
from cellctl.pick.model import PartModel
from cellctl.pick.model_schema import PartModelDoc
from cellctl.production.config import ConveyorSource, GripperDevice, PlaceSection
from cellctl.strict_types import Bool, Count, Num


class PickError(CellctlError, ValueError):
    """The pick cannot be done as asked (no calibration, bad recipe, image of the wrong size...)."""


# Bounds of numbers a recipe may hold (the edge refuses the rest with 422 naming the field).
MAX_COORD_MM = 1e5
"""Lengths and heights, mm: nothing in a work cell is 100 m away."""
MIN_SCORE_FLOOR = 0.3
"""Below this a match score accepts noise (or the edge of whatever lies there) as a part, and the search tries
every position: a production cell would pick at shadows."""
MAX_NAME_CHARS = 200
"""A recipe's name is a label an operator reads on a panel, not a document."""
MIN_SPEED_M_S = 0.001
"""A pick slower than 1 mm/s cannot be supervised (and would outlast any move deadline)."""

# Strict numbers (cellctl.strict_types): a JSON number, never a bool or a string, finite and in range.
Mm = Annotated[Num, Field(ge=-MAX_COORD_MM, le=MAX_COORD_MM)]
Px = Annotated[Num, Field(ge=-1e5, le=1e5)]
Deg = Annotated[Num, Field(ge=-360.0, le=360.0)]
Rad = Annotated[Num, Field(ge=-2 * math.pi, le=2 * math.pi)]
Scale = Annotated[Num, Field(ge=0.5, le=2.0)]


class SearchSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    min_score: Num = Field(0.6, le=1, description=f"lowest score of a match, {MIN_SCORE_FLOOR}..1")
    max_count: Count = Field(5, ge=1, le=100)
    angle_start_deg: Deg = -180.0
    angle_extent_deg: Num = Field(360.0, gt=0, le=360)
    roi: tuple[Px, Px, Px, Px] | None = None
    timeout_s: Num | None = Field(1.0, gt=0, le=60)
    polarity: Literal["use_polarity", "ignore_global_polarity", "ignore_local_polarity"] = Field(
        "ignore_local_polarity", description="use_polarity: edges keep the teach image's contrast; "
        "ignore_global_polarity: or all reversed (an inverted image); ignore_local_polarity: each edge either way")
    greediness: Num = Field(0.9, ge=0, le=1, description="0: safe, slower; 1: fast, may miss weak parts")
    scale_range: tuple[Scale, Scale] = Field((1.0, 1.0), description="isotropic scales searched, e.g. "
                                             "[0.9, 1.1]; [1, 1]: none")
    mirrored: Bool = Field(False, description="also find the part face down (mirrored)")
    max_overlap: Num = Field(0.5, ge=0, le=1, description="largest overlap of two matches' boxes, 0..1")
    min_surround: Num = Field(0.2, ge=-1, le=1, description="how far the seen edges must enclose the part's "
                              "centre (1 all round, ~0 a half; 0.2 refuses halves; -1: no check)")

    @field_validator("scale_range")
    @classmethod
    def _scale_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0.5 <= v[0] <= v[1] <= 2.0):
            raise ValueError(f"scale_range {list(v)} must be [low, high] with 0.5 <= low <= high <= 2")
        return v

    @field_validator("min_score")
    @classmethod
    def _min_score(cls, v: float) -> float:
        if not v >= MIN_SCORE_FLOOR:
            raise ValueError(f"min_score {v:g} is below {MIN_SCORE_FLOOR:g}, the least a cell allows: at scores like "
                             "0.05 the search takes noise and the edges of whatever lies there for parts and tries "
                             "every position; use 0.3..0.9 (default 0.6)")
        return v


class GripperSettings(BaseModel):
    """How the gripper takes the part (read by the pick motion; None: the cell's default)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    open_width_mm: Num | None = Field(None, ge=0, le=1000, description="opening before the approach, mm")
    grip_width_mm: Num | None = Field(None, ge=0, le=1000, description="closing width at the grasp, mm")
    force_n: Num | None = Field(None, ge=0, le=1000, description="grip force, N")
    settle_s: Num = Field(0.2, ge=0, le=10, description="wait after closing before lifting, s")
    io_output: str | None = Field(None, max_length=64, description="digital output that closes the gripper "
                                                                    "(a configured io device's channel name)")
    device: GripperDevice | None = Field(None, description="the gripper's io device and its grip check "
                                                           "(docs/production.md); none: the pick does not grip")


class Recipe(BaseModel):
    """What to pick and how (stored versioned in the store under a PLC recipe number)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: str = Field(min_length=1, max_length=MAX_NAME_CHARS, description=f"a label, 1-{MAX_NAME_CHARS} characters")
    models: list[PartModelDoc] = Field(min_length=1, max_length=16,
                                     description="part models (cellctl pick teach output)")
    camera_id: str | None = None
    robot_id: str | None = None
    calibration: Literal["auto", "handeye", "npoint"] = "auto"
    plane_z_mm: Mm | None = Field(None, description="height of the parts' top face in the base frame, mm")
    grasp_offset_mm: tuple[Mm, Mm] = (0.0, 0.0)
    """Grasp point from the part's reference point, in the part's frame (x along its taught x), mm."""
    grasp_z_mm: Mm = 0.0
    """Tool z above the working plane at the grasp, mm."""
    approach_height_mm: Num = Field(50.0, ge=0, le=MAX_COORD_MM)
    grasp_yaw_deg: Deg = 0.0
    gripper_symmetry_deg: Num = Field(180.0, gt=0, le=360)
    tool_rotvec_rad: tuple[Rad, Rad, Rad] = (math.pi, 0.0, 0.0)
    """Tool orientation at gripper yaw 0 (default: pointing down, tool x along base x)."""
    speed_m_s: Num = Field(0.1, ge=MIN_SPEED_M_S, le=2)
    search: SearchSettings = SearchSettings()
    capture_pose_ur: tuple[Mm, Mm, Mm, Rad, Rad, Rad] | None = Field(
        None, description="robot pose to take the picture from, UR form [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad] "
                          "(metres, rotation vector in radians); taught with the part, usually read from the robot")
    gripper: GripperSettings = GripperSettings()
    place: PlaceSection | None = Field(None, description="where picked parts go (fixed, grid or located; "
                                                         "docs/production.md); none: the recipe only picks")
    source: ConveyorSource | None = Field(None, description="where parts come from: absent, a still pick area; "
                                                          "{kind: conveyor, ...}: a moving belt (docs/conveyor.md)")
    tool_centre_offset_mm: tuple[Mm, Mm] | None = Field(
        None, description="the gripper's centre from the flange axis, as `cellctl calib tcp` reports it "
                          "(offset_mm: tool x/y along base x/y at tool rz = 0), mm; the pick poses then put "
                          "the gripper's centre, not the flange, on the part")

    @field_validator("capture_pose_ur")
    @classmethod
    def _capture_pose_in_metres(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and any(abs(x) > 20.0 for x in v[:3]):
            raise ValueError(f"capture_pose_ur translation {list(v[:3])} looks like millimetres: the UR form is in "
                             "metres (e.g. [0.4, 0.0, 0.55, 3.1416, 0, 0])")
        return v

    @field_serializer("models")
    def _models_as_given(self, models: list[PartModelDoc]) -> list[dict[str, Any]]:
        return [m.model_dump(mode="json") for m in models]

    def part_models(self) -> list[PartModel]:
        return [PartModel.from_dict(m.model_dump(mode="json"), f"recipe {self.name} model {k}")
                for k, m in enumerate(self.models)]
