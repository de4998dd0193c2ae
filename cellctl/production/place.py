"""Pick and place poses of one part: the tool holds the part at pick as it must hold it at the place.

A match gives the part's pose in the base frame (``T_base_part``: the reference point mapped onto
the working plane ``plane_z_mm``, the taught x axis's direction). The gripper holds the part at
``T_part_grip = Trans(grasp_offset_mm, grasp_z_mm) @ Rz(grasp_yaw + k * symmetry) @ R_tool0`` (the
recipe's grasp, in the part's frame); the pick is ``T_base_part @ T_part_grip`` and the place
``T_slot @ T_part_grip``, so the part arrives at the slot with the slot's yaw whatever its yaw at
pick. Of the gripper's symmetric grasps (``k``) the one nearest the tool's current yaw is used,
for the pick and the place alike (the turn between them is the part's, whichever ``k``). With a
``tool_centre_offset_mm`` the poses found are the gripper centre's, and the flange is commanded.
Every pose (pick, place and their approaches) goes through the robot's envelope and orientation
checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.handeye import flange_pose_for_feature, tool_offset_vector
from cellctl.mapping import ActiveMapping
from cellctl.pick.pose import pick_pose
from cellctl.pick.recipe import Recipe
from drivers.base import MotionLimits, MotionRejected

Mat4 = NDArray[np.float64]


@dataclass
class Plan:
    """One part's poses (``T_base_tool``, metres) and what the vision said about it."""

    T_base_part: Mat4
    T_pick: Mat4
    T_pick_approach: Mat4
    T_part_grip: Mat4
    sigma_mm: list[float]
    sigma_yaw_deg: float
    problem: str | None = None
    """Why this part cannot be picked (a pose outside the envelope, ...); None when it can."""

    def place(self, recipe: Recipe, T_slot: Mat4, limits: MotionLimits) -> tuple[Mat4, Mat4]:
        """(place, place approach) poses of the tool for the part at ``T_slot``; MotionRejected when refused."""
        T_place = _flange(recipe, T_slot @ self.T_part_grip)
        height_mm = recipe.approach_height_mm
        if recipe.place is not None and recipe.place.approach_height_mm is not None:
            height_mm = recipe.place.approach_height_mm
        T_app = T_place.copy()
        T_app[2, 3] += height_mm * 1e-3
        for T, what in ((T_place, "place"), (T_app, "pre-place")):
            try:
                limits.check_pose(T)
            except MotionRejected as exc:
                raise MotionRejected(f"the {what} pose is refused: {exc}") from None
        return T_place, T_app


def _flange(recipe: Recipe, T_grip: Mat4) -> Mat4:
    if recipe.tool_centre_offset_mm is None:
        return T_grip
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    return flange_pose_for_feature(T_grip, tool_offset_vector(recipe.tool_centre_offset_mm, R0))


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def plan_part(mapping: ActiveMapping, recipe: Recipe, match: dict[str, Any], T_capture: Mat4 | None,
              current_yaw: float, limits: MotionLimits) -> Plan:
    """The pick of one match (``u_px``, ``v_px``, ``angle_deg``), its grasp, and whether it is reachable."""
    u, v, angle = float(match["u_px"]), float(match["v_px"]), float(match["angle_deg"])
    sigma_angle = match.get("sigma_angle_deg")
    pp = pick_pose(mapping, recipe, u, v, angle, T_capture, current_yaw,
                   float("nan") if sigma_angle is None else float(sigma_angle))
    z_mm = recipe.plane_z_mm if recipe.plane_z_mm is not None else 0.0
    p0 = mapping.map(np.array([u, v]), recipe.plane_z_mm, T_capture, with_uncertainty=False).xyz_mm
    part_yaw = math.radians(pp["base_yaw_deg"])  # the part's taught x axis in the base frame
    T_part = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, part_yaw]), [p0[0] * 1e-3, p0[1] * 1e-3, z_mm * 1e-3])
    sym = math.radians(recipe.gripper_symmetry_deg)
    n = max(1, round(2 * math.pi / sym))
    grasp = math.radians(recipe.grasp_yaw_deg)
    k = min(range(n), key=lambda j: abs(_wrap(part_yaw + grasp + j * sym - current_yaw)))
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    ox, oy = recipe.grasp_offset_mm
    T_part_grip = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, grasp + k * sym]) @ R0,
                                   [ox * 1e-3, oy * 1e-3, recipe.grasp_z_mm * 1e-3])
    T_pick = _flange(recipe, T_part @ T_part_grip)
    T_app = T_pick.copy()
    T_app[2, 3] += recipe.approach_height_mm * 1e-3
    problem = None
    for T, what in ((T_pick, "pick"), (T_app, "pre-pick")):
        try:
            limits.check_pose(T)
        except MotionRejected as exc:
            problem = f"the {what} pose is refused: {exc}"
            break
    sigma_yaw = pp["sigma_yaw_deg"]
    return Plan(T_part, T_pick, T_app, T_part_grip, [float(s) for s in pp["sigma_mm"] if s is not None],
                float("nan") if sigma_yaw is None else float(sigma_yaw), problem)
