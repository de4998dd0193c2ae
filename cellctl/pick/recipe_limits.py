"""A recipe checked against the cell it is saved for: what the cell's robot allows, before it is stored.

``POST /recipes`` refuses (422 ``recipe_outside_cell``) a recipe that could only fail when run
(issue 34): a degenerate grid (``cellctl.production.config.grid_problem``: over 10,000 slots, or
neighbouring slots closer than 1 mm), a ``speed_m_s`` above the robot's ``max_linear_speed_m_s``
(cell.yaml), or a place that puts the tool outside the robot's envelope or tool cone — a fixed
place's pose, or any corner slot of a grid (first and last row, column and layer), each with its
approach above it. The
tool's pose at a slot is the recipe's grasp applied to the part's pose there (as a run computes it,
``cellctl.production.place``); a located place moves with its fixture and is checked at each pick.
"""

from __future__ import annotations

from itertools import product

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.config import CellConfig
from cellctl.pick.pose import flange_pose
from cellctl.pick.recipe import PickError, Recipe
from cellctl.production.config import FixedPlace, GridPlace, LocatedPlace, grid_problem
from drivers.base import MotionRejected


class RecipeOutsideCell(PickError):
    """The recipe asks what the cell's robot does not allow; the message names the value and the limit."""


def check_recipe_for_cell(recipe: Recipe, config: CellConfig) -> None:
    """Raise :class:`RecipeOutsideCell` when ``recipe`` asks more than the cell's robot allows."""
    place = recipe.place
    if isinstance(place, GridPlace | LocatedPlace):
        problem = grid_problem(place.rows, place.cols, place.layers, place.pitch_mm, place.layer_mm)
        if problem is not None:
            raise RecipeOutsideCell(f"place: {problem}")
    robot_id = recipe.robot_id or config.calibration.robot
    robot = config.robots.get(robot_id) if robot_id else None
    if robot is None:
        return  # no robot to move: the pick answers poses only (and an unknown robot is refused when used)
    limits = robot.limits()
    if recipe.speed_m_s > limits.max_linear_speed_m_s:
        raise RecipeOutsideCell(f"speed_m_s {recipe.speed_m_s:g} is above robot {robot_id}'s max_linear_speed_m_s "
                                f"{limits.max_linear_speed_m_s:g} m/s (cell.yaml): give at most that")
    if isinstance(place, FixedPlace):
        slots = [(0, "the place pose")]
    elif isinstance(place, GridPlace):
        slots = [(l_ * place.rows * place.cols + r * place.cols + c, f"slot (row {r}, col {c}, layer {l_})")
                 for l_, r, c in sorted(set(product({0, place.layers - 1}, {0, place.rows - 1}, {0, place.cols - 1})))]
    else:
        return
    height_mm = recipe.approach_height_mm if place.approach_height_mm is None else place.approach_height_mm
    grip = _part_grip(recipe)
    for k, what in slots:
        T_place = flange_pose(recipe, place.T_slot(k) @ grip)
        T_app = T_place.copy()
        T_app[2, 3] += height_mm * 1e-3
        for T, which in ((T_place, "place"), (T_app, "pre-place")):
            try:
                limits.check_pose(T)
            except MotionRejected as exc:
                raise RecipeOutsideCell(f"place: the tool's {which} pose at {what} is refused by robot {robot_id}: "
                                        f"{exc}") from None


def _part_grip(recipe: Recipe) -> NDArray[np.float64]:
    """``T_part_grip`` at the recipe's grasp yaw (the symmetric grasps differ by a turn about z only)."""
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    ox, oy = recipe.grasp_offset_mm
    return g.make_transform(g.rotvec_to_matrix([0.0, 0.0, np.radians(recipe.grasp_yaw_deg)]) @ R0,
                            [ox * 1e-3, oy * 1e-3, recipe.grasp_z_mm * 1e-3])
