"""Production's part of a recipe: the ``place`` section and the gripper's device (where parts go,
and how a grip is checked). Production owns them; the recipe (``cellctl.pick.recipe``) carries them
under ``place`` and ``gripper.device``, its JSON unchanged.

Place poses are where the **part** goes (its reference point on its top face, its taught x axis
along the pose's x), in the robot base frame, UR form (metres, rotation vector in radians):

- ``fixed``: one pose, every part goes there;
- ``grid``: slot ``k = l*R*C + r*C + c`` (0-based, row-major, then layer) at
  ``T_origin @ Trans(c*px, r*py, l*h)`` (mm in the origin's frame).

- ``located``: a place found by vision in the same picture as the parts: a second taught model
  (``model``, e.g. a fixture or a tray) is searched; its pose (its taught reference point mapped
  onto ``plane_z_mm``, its taught x axis) is ``T_base_fixture``, and slot ``k`` is
  ``T_base_fixture @ T_origin @ Trans(c*px, r*py, l*h)`` with ``origin_ur`` in the fixture's frame
  (a grid of ``rows`` x ``cols`` x ``layers`` as above; 1 x 1 x 1 by default: one place).

The gripper's device (``GripperDevice``) names a configured ``io`` device and how to drive and
check it: ``robotiq_2f`` (a Robotiq 2F gripper or the virtual cell's ``sim_gripper``: the
object-detected status, and the closed width within ``width_tolerance_mm`` of the recipe's
``grip_width_mm`` when that is given), ``vacuum`` (a digital output switches the vacuum, a vacuum
switch input says the cup holds) or ``parallel`` (two outputs close and open the fingers, a
"closed on part" input says they hold something).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from calibration import geometry as g
from cellctl.pick.model_schema import PartModelDoc
from cellctl.strict_types import Count, Num

UR = tuple[Num, Num, Num, Num, Num, Num]
"""A UR pose; strict numbers (cellctl.strict_types): a JSON number, never a bool or a string."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


MAX_SLOTS = 10_000
"""Slots of one grid at most (rows x cols x layers): no tray or pallet holds more."""
MIN_PITCH_MM = 1.0
"""Neighbouring slots at least this far apart (a pitch of 0 puts every part in one place)."""


def grid_problem(rows: int, cols: int, layers: int, pitch_mm: tuple[float, float], layer_mm: float) -> str | None:
    """Why a grid is degenerate (too many slots, or two slots in one place); None when it is not.

    Checked when a recipe is saved (``cellctl.pick.recipe_limits``), not by the models themselves: a
    place section may be built step by step (a located place is found before its pitch is known)."""
    n = rows * cols * layers
    if n > MAX_SLOTS:
        return (f"the grid has {n} slots ({rows} rows x {cols} cols x {layers} layers), more than {MAX_SLOTS}: "
                "give the tray's real rows, cols and layers")
    for count, value, what in ((cols, pitch_mm[0], "pitch_mm[0] (between columns)"),
                               (rows, pitch_mm[1], "pitch_mm[1] (between rows)"), (layers, layer_mm, "layer_mm")):
        if count > 1 and abs(value) < MIN_PITCH_MM:
            return (f"{what} is {value:g} mm with {count} of them: slots closer than {MIN_PITCH_MM:g} mm put parts "
                    "into one another; give the tray's pitch in mm")
    return None


def _metres(v: UR, what: str) -> UR:
    if any(abs(x) > 20.0 for x in v[:3]):
        raise ValueError(f"{what} translation {list(v[:3])} looks like millimetres: the UR form is in metres "
                         "(e.g. [0.4, -0.2, 0.006, 0, 0, 0])")
    if any(abs(x) > 2 * np.pi for x in v[3:]):
        raise ValueError(f"{what} rotation {list(v[3:])} is not a rotation vector in radians")
    return v


class FixedPlace(_Strict):
    kind: Literal["fixed"]
    pose_ur: UR = Field(description="where the part goes: [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad], base frame")
    approach_height_mm: Num | None = Field(None, ge=0, le=1000, description="pre-/post-place height above the "
                                                                              "place, mm (default: the recipe's)")

    @field_validator("pose_ur")
    @classmethod
    def _pose(cls, v: UR) -> UR:
        return _metres(v, "pose_ur")

    def slot_count(self) -> int | None:
        return None  # every part goes to the one pose

    def T_slot(self, k: int) -> NDArray[np.float64]:
        return g.ur_pose_to_transform(list(self.pose_ur))


class GridPlace(_Strict):
    kind: Literal["grid"]
    origin_ur: UR = Field(description="slot 0's pose, UR form (m, rad), base frame")
    rows: Count = Field(ge=1, le=1000)
    cols: Count = Field(ge=1, le=1000)
    pitch_mm: tuple[Num, Num] = Field(description="[px, py]: column and row pitch in the origin's frame, mm")
    layers: Count = Field(1, ge=1, le=1000)
    layer_mm: Num = Field(0.0, ge=0, le=1000, description="height of one layer (stacking), mm")
    approach_height_mm: Num | None = Field(None, ge=0, le=1000)

    @field_validator("origin_ur")
    @classmethod
    def _pose(cls, v: UR) -> UR:
        return _metres(v, "origin_ur")

    @field_validator("pitch_mm")
    @classmethod
    def _pitch(cls, v: tuple[float, float]) -> tuple[float, float]:
        if any(abs(x) > 1e4 for x in v):
            raise ValueError(f"pitch_mm {list(v)} is more than 10 m")
        return v

    def slot_count(self) -> int:
        return self.rows * self.cols * self.layers

    def T_slot(self, k: int) -> NDArray[np.float64]:
        """Slot ``k``'s pose (the part's), 4x4 metres."""
        n = self.slot_count()
        if not 0 <= k < n:
            raise ValueError(f"slot {k} is not in the grid's 0..{n - 1}")
        layer, rest = divmod(k, self.rows * self.cols)
        r, c = divmod(rest, self.cols)
        offset = np.array([c * self.pitch_mm[0], r * self.pitch_mm[1], layer * self.layer_mm]) * 1e-3
        return g.ur_pose_to_transform(list(self.origin_ur)) @ g.make_transform(np.eye(3), offset)


class LocatedPlace(_Strict):
    kind: Literal["located"]
    model: PartModelDoc = Field(description="the fixture's model, taught like a part (POST /pick/teach's answer)")
    plane_z_mm: Num = Field(ge=-10_000, le=10_000, description="height of the fixture's top face in the base "
                                                               "frame, mm (where its model is mapped)")
    min_score: Num = Field(0.6, ge=0.3, le=1, description="lowest score the fixture is found with")
    roi: tuple[Num, Num, Num, Num] | None = Field(None, description="search region of the fixture's reference "
                                                                     "point [u, v, w, h], image px; none: all")
    origin_ur: UR = Field(description="slot 0's pose in the fixture's frame (its reference point, taught x "
                                      "axis), UR form (m, rad): where the part's reference point goes")
    rows: Count = Field(1, ge=1, le=1000)
    cols: Count = Field(1, ge=1, le=1000)
    pitch_mm: tuple[Num, Num] = Field((0.0, 0.0), description="[px, py] in the origin's frame, mm")
    layers: Count = Field(1, ge=1, le=1000)
    layer_mm: Num = Field(0.0, ge=0, le=1000)
    approach_height_mm: Num | None = Field(None, ge=0, le=1000)

    @field_validator("origin_ur")
    @classmethod
    def _pose(cls, v: UR) -> UR:
        return _metres(v, "origin_ur")

    def slot_count(self) -> int:
        return self.rows * self.cols * self.layers

    def T_slot_in_fixture(self, k: int) -> NDArray[np.float64]:
        """Slot ``k``'s pose in the fixture's frame, 4x4 metres."""
        grid = GridPlace(kind="grid", origin_ur=self.origin_ur, rows=self.rows, cols=self.cols,
                         pitch_mm=self.pitch_mm, layers=self.layers, layer_mm=self.layer_mm)
        return grid.T_slot(k)

    def T_slot(self, k: int) -> NDArray[np.float64]:
        raise ValueError("a located place's slots are found with the fixture in each picture (T_slot_in_fixture)")


PlaceSection = Annotated[FixedPlace | GridPlace | LocatedPlace, Field(discriminator="kind")]


class ConveyorSource(_Strict):
    """A recipe's ``source``: the parts come on a belt (docs/conveyor.md); absent: a still pick area."""

    kind: Literal["conveyor"]
    conveyor_id: str = Field("belt0", min_length=1, max_length=64, description="the belt (the config's conveyors)")
    window_mm: tuple[Num, Num] | None = Field(None, description="base x (mm) where the robot may meet a part on "
                                                                "the belt (default: the belt's pick_window_mm)")
    idle_timeout_s: Num = Field(30.0, gt=0, le=3600, description="a run with count 0 ends area_empty when the "
                                                                 "belt brought no part for this long, s")
    accel_m_s2: Num = Field(2.0, gt=0, le=50, description="the robot's linear acceleration the meeting is "
                                                          "planned with, m/s^2")

    @model_validator(mode="after")
    def _window(self) -> ConveyorSource:
        if self.window_mm is not None and not self.window_mm[0] < self.window_mm[1]:
            raise ValueError("window_mm must be [x_start, x_end] with x_start < x_end (base x, mm)")
        return self


class GripperDevice(_Strict):
    """The gripper's device and how its grip is checked (see the module docstring)."""

    io_id: str = Field(min_length=1, max_length=128, description="a configured io device (cell.yaml io:)")
    kind: Literal["robotiq_2f", "vacuum", "parallel"] = Field(
        description="robotiq_2f: a Robotiq 2F or the sim gripper; vacuum: output on/off and a vacuum switch input; "
                    "parallel: close and open outputs and a 'closed on part' input")
    output: Count | None = Field(None, ge=0, le=65535, description="vacuum: the vacuum output; parallel: the close "
                                                                 "output")
    open_output: Count | None = Field(None, ge=0, le=65535, description="parallel: the open output; vacuum: an "
                                                                      "optional blow-off output pulsed at release")
    input: Count | None = Field(None, ge=0, le=65535, description="vacuum: the vacuum switch; parallel: 'closed on "
                                                                "part'")
    stroke_mm: Num = Field(85.0, gt=0, le=1000, description="robotiq_2f: the fingers' full opening, mm")
    width_tolerance_mm: Num = Field(3.0, gt=0, le=100, description="robotiq_2f with grip_width_mm: the closed "
                                                                     "width must be this close to it, mm")
    release_s: Num = Field(0.1, ge=0, le=10, description="wait after opening before the tool leaves, s")
    clearance_mm: Num | None = Field(None, gt=0, le=1000, description="a part whose reference point has another "
                                                                     "found part's nearer than this is not picked "
                                                                     "(the gripper would hit the neighbour); none: "
                                                                     "not checked")
    retries: Count = Field(2, ge=0, le=20, description="a part whose grip fails is tried again (from a fresh picture) "
                                                     "this many times before it is skipped")
    input_timeout_s: Num = Field(1.0, gt=0, le=30, description="vacuum/parallel: how long the check waits for "
                                                                 "its input, s")

    @model_validator(mode="after")
    def _channels(self) -> GripperDevice:
        if self.kind == "vacuum" and (self.output is None or self.input is None):
            raise ValueError("a vacuum gripper needs output (the vacuum) and input (the vacuum switch)")
        if self.kind == "parallel" and (self.output is None or self.open_output is None or self.input is None):
            raise ValueError("a parallel gripper needs output (close), open_output (open) and input (closed on part)")
        return self
