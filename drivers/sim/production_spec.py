"""The ``production:`` section of a scene file: parts a sim gripper picks up and puts down.

A production scene scatters ``scatter.count`` copies of one flat part (``part``) over a pick area
on the table (seeded: touching, turned, some against the area's edge; one part may be set clear of
the others so that it can be taught), and names a place area beside it with a place grid that fits
it. ``gripper`` says when the sim gripper holds what it closes on, and the faults it plays.

Lengths are millimetres (``*_mm``) in the robot base frame unless named otherwise; the place
grid's origin is in the UR form (metres, rotation vector in radians), as a recipe's place section.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Range = Annotated[tuple[float, float], Field(description="[low, high], mm")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class PartTemplate(_Strict):
    """The flat part every scattered copy is: its outline in its own frame (mm).

    The part's frame has its origin at the reference point (the centre of the outline's bounding
    box, so a ROI drawn around an upright part has it at its centre) on the part's top face, x and
    y in the outline's axes.
    """

    name: str = "part"
    outline_mm: list[list[float]] = Field(min_length=3)
    holes_mm: list[list[list[float]]] = []
    reflectance: float = Field(0.9, ge=0, le=1)
    thickness_mm: float = Field(6.0, gt=0, le=200)
    grip_width_mm: float = Field(30.0, gt=0, le=500)
    """The part's width between a parallel gripper's fingers (what a closed 2-finger gripper reads)."""

    @field_validator("outline_mm")
    @classmethod
    def _centred(cls, v: list[list[float]]) -> list[list[float]]:
        if any(len(p) != 2 for p in v):
            raise ValueError("outline_mm must be a list of [x, y] pairs")
        xs, ys = [p[0] for p in v], [p[1] for p in v]
        if abs(max(xs) + min(xs)) > 1e-6 or abs(max(ys) + min(ys)) > 1e-6:
            raise ValueError("the outline's bounding box must be centred on the part's origin (its reference "
                             "point): shift the outline so that min x = -max x and min y = -max y")
        return v


class AreaSpec(_Strict):
    """A rectangle on the table, base frame, mm."""

    x_mm: Range
    y_mm: Range

    @model_validator(mode="after")
    def _ordered(self) -> AreaSpec:
        if not (self.x_mm[0] < self.x_mm[1] and self.y_mm[0] < self.y_mm[1]):
            raise ValueError("an area's x_mm and y_mm must be [low, high] with low < high")
        return self

    def contains(self, x_mm: float, y_mm: float, margin_mm: float = 0.0) -> bool:
        return (self.x_mm[0] - margin_mm <= x_mm <= self.x_mm[1] + margin_mm
                and self.y_mm[0] - margin_mm <= y_mm <= self.y_mm[1] + margin_mm)


class ClearPartSpec(_Strict):
    """One part set apart from the others (upright: ``angle_deg`` 0 by default), to be taught."""

    x_mm: float
    y_mm: float
    angle_deg: float = 0.0
    clearance_mm: float = Field(25.0, ge=0, le=500)
    """No other part comes nearer than this to its outline, mm."""


class ScatterSpec(_Strict):
    count: int = Field(12, ge=0, le=200)
    """Parts in the pick area (the clear part included)."""
    seed: int = Field(0, ge=0)
    touching: float = Field(0.5, ge=0, le=1)
    """Fraction of the parts slid against a neighbour (or the area's edge) after they are dropped."""
    clear_part: ClearPartSpec | None = None


class FixedPartSpec(_Strict):
    """A part at a given place (e.g. one the robot cannot reach)."""

    x_mm: float
    y_mm: float
    angle_deg: float = 0.0


class PlaceGridSpec(_Strict):
    """A grid place section (a recipe's ``place``): slot k = l*R*C + r*C + c at origin * Trans(c px, r py, l h)."""

    origin_ur: Annotated[list[float], Field(min_length=6, max_length=6)]
    rows: int = Field(ge=1, le=100)
    cols: int = Field(ge=1, le=100)
    pitch_mm: tuple[float, float]
    layers: int = Field(1, ge=1, le=100)
    layer_mm: float = Field(0.0, ge=0, le=1000)


class SimGripperSpec(_Strict):
    """When the sim gripper holds what it closes on, and the faults it plays (seeded by the scene)."""

    tolerance_mm: float = Field(3.0, gt=0, le=50)
    """The gripper's centre (the robot's TCP) must be this close to the part's reference point, in x/y."""
    tolerance_deg: float = Field(6.0, gt=0, le=90)
    """... and the tool's yaw this close to the part's (modulo ``symmetry_deg``)."""
    symmetry_deg: float = Field(180.0, gt=0, le=360)
    above_mm: float = Field(3.0, ge=0, le=100)
    """... and its z at most this far above the part's top face (and not below its bottom)."""
    open_width_mm: float = Field(85.0, gt=0, le=1000)
    """The fingers' opening (a Robotiq 2F-85's stroke by default); closed empty reads 0."""
    actuation_s: float = Field(0.15, ge=0, le=10)
    """Time to close or open (scaled like the robot's moves by the sim gripper's time scale)."""
    fail_probability: float = Field(0.0, ge=0, le=1)
    """A close on a part slips off it (closes empty) with this probability: each close on a part draws
    once from the fault stream (independent draws, seeded: ``fail_seed``)."""
    fail_seed: int | None = Field(None, ge=0)
    """The fault stream's seed; default the scene's ``seed`` with the scatter's, so that every scatter
    (a bench's seeds) draws its own faults and the same scene always draws the same."""
    slip_accel_m_s2: float | None = Field(None, gt=0, le=1000)
    """A held part slips out at a move whose start acceleration reaches this (none: never)."""
    accel_ramp_s: float = Field(0.1, gt=0, le=10)
    """The arm reaches a move's speed in this time: its acceleration is speed / ramp."""


class FixtureSpec(_Strict):
    """A nest plate lying on the table, for a place found by vision (a recipe's ``located`` place):
    a flat plate (its outline, in its own frame, mm) with pockets through it (``holes_mm``) that a
    part drops into; ``slots_mm`` are the pockets' centres, where a placed part's reference point goes."""

    outline_mm: list[tuple[float, float]] = Field(min_length=3)
    holes_mm: list[list[tuple[float, float]]] = []
    slots_mm: list[tuple[float, float]] = Field(min_length=1)
    x_mm: float
    y_mm: float
    angle_deg: float = 0.0
    height_mm: float = Field(1.0, gt=0, le=50)
    """The plate's thickness: its top face is this far above the table (a placed part lies on the table)."""
    reflectance: float = Field(0.45, ge=0, le=1)

    def T_base_fixture(self, table_z_m: float) -> list[list[float]]:
        """The plate's frame on its top face (4x4, metres): origin at (x_mm, y_mm), x axis at angle_deg."""
        a = math.radians(self.angle_deg)
        return [[math.cos(a), -math.sin(a), 0.0, self.x_mm * 1e-3],
                [math.sin(a), math.cos(a), 0.0, self.y_mm * 1e-3],
                [0.0, 0.0, 1.0, table_z_m + self.height_mm * 1e-3], [0.0, 0.0, 0.0, 1.0]]

    def contains(self, x_mm: float, y_mm: float) -> bool:
        """True when the base-frame point lies on the plate (its outline, pockets included)."""
        a = math.radians(self.angle_deg)
        dx, dy = x_mm - self.x_mm, y_mm - self.y_mm
        u, v = math.cos(a) * dx + math.sin(a) * dy, -math.sin(a) * dx + math.cos(a) * dy
        inside = False
        pts = self.outline_mm
        for (x0, y0), (x1, y1) in zip(pts, [*pts[1:], pts[0]], strict=True):
            if (y0 > v) != (y1 > v) and u < x0 + (v - y0) * (x1 - x0) / (y1 - y0):
                inside = not inside
        return inside


class ProductionSpec(_Strict):
    """Parts as objects: a seeded scatter over the pick area, a place area and grid, a gripper."""

    part: PartTemplate
    pick_area: AreaSpec
    place_area: AreaSpec
    place_grid: PlaceGridSpec
    scatter: ScatterSpec = ScatterSpec()
    unreachable: list[FixedPartSpec] = []
    """Parts lying where the cell's robot cannot reach them (outside its envelope), in the camera's view."""
    gripper: SimGripperSpec = SimGripperSpec()
    fixture: FixtureSpec | None = None
    """A nest plate for a place found by vision (none: the scene has none)."""

    def part_radius_mm(self) -> float:
        return max(math.hypot(p[0], p[1]) for p in self.part.outline_mm)
