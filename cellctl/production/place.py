"""Place poses of one part: the tool holds the part at the place as it held it at pick.

A pick's candidate (``cellctl.pick.candidate.PickCandidate``) carries the part's pose
``T_base_part`` and the grasp ``T_part_grip`` (the recipe's grasp in the part's frame, folded to the
gripper's symmetric grasp nearest the tool's yaw: ``cellctl.pick.pose.grasp``); the place is
``T_slot @ T_part_grip``, so the part arrives at the slot with the slot's yaw whatever its yaw at
pick (the turn between pick and place is the part's, whichever symmetric grasp). With a
``tool_centre_offset_mm`` the poses found are the gripper centre's, and the flange is commanded.
Every pose (place and its approach) goes through the robot's envelope and orientation checks.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cellctl.pick.candidate import PickCandidate
from cellctl.pick.recipe import Recipe
from drivers.base import MotionLimits, MotionRejected

Mat4 = NDArray[np.float64]


def place_poses(recipe: Recipe, cand: PickCandidate, T_slot: Mat4, limits: MotionLimits) -> tuple[Mat4, Mat4]:
    """(place, place approach) poses of the tool for the part ``cand`` at ``T_slot``; MotionRejected when
    refused."""
    T_place = T_slot @ cand.T_part_grip @ cand.T_grip_flange
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
