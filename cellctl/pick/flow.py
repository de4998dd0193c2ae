"""The pick flow: grab, locate the recipe's parts, convert each match to a gripper pose, check it.

Every pose — pick and approach — is checked against the robot's envelope; a pose outside it is
reported ``reachable: false`` and never sent. Locating (grab, search, a ``PickCandidate`` per match)
is ``cellctl.pick.candidate``; the conversion of a match to a pose ``cellctl.pick.pose``; the
recipe ``cellctl.pick.recipe``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.mapping import active_mapping
from cellctl.motion import audited_move, halt_after_failure
from cellctl.pick.candidate import camera_of, locate
from cellctl.pick.pose import fold_yaw, pick_pose, pose_json
from cellctl.pick.recipe import PickError, Recipe, SearchSettings
from cellctl.services import Services
from drivers.base import RobotBase

__all__ = ["PickError", "Recipe", "SearchSettings", "fold_yaw", "locate", "pick_pose", "pose_json", "run_pick"]


def run_pick(services: Services, recipe_id: int, camera_id: str | None = None, move: bool = False,
             who: str = "plc") -> dict[str, Any]:
    """Grab, locate, convert, check; with ``move`` the robot picks the best reachable match.

    With ``move`` the pick owns the robot's motion from before the grab to the retreat (a second
    mover gets ``RobotBusy``); a Stop aborts it (``RobotStopped``) and nothing more is moved.
    """
    stored = services.store.get_recipe(recipe_id)
    recipe = Recipe.model_validate(stored.data)
    robot_id = recipe.robot_id or services.config.calibration.robot
    robot: RobotBase = services.cell.robot(robot_id).ensure_open()
    if not move:
        T_capture = _capture_pose(recipe)
        off = None if T_capture is None else _off_pose(robot, T_capture)
        if off is not None:
            raise PickError(f"the robot is {off} from recipe {recipe_id}'s capture pose: the parts would be "
                            "seen from the wrong place; move it there, or pick with move: true (which goes there "
                            "first)")
        if not active_mapping(services, camera_of(services, recipe, camera_id), robot_id, recipe.calibration,
                              recipe.plane_z_mm is not None).camera_on_arm:
            return locate(services, recipe_id, stored.version, recipe, camera_id, robot).answer()
        # A camera on the arm measures only while the arm stands still: hold it (RobotBusy while another
        # caller moves it), so the frame and the pose read with it belong together.
        still = robot.motion.begin(who, f"pick of recipe {recipe_id}: locating", still=True)
        try:
            return locate(services, recipe_id, stored.version, recipe, camera_id, robot).answer()
        finally:
            robot.motion.end(still)
    with robot.motion_session(who, f"pick of recipe {recipe_id}") as session:
        T_capture = _capture_pose(recipe)
        if T_capture is not None and _off_pose(robot, T_capture) is not None:
            audited_move(services.store, who, robot, T_capture, recipe.speed_m_s, "pick: to the capture pose", session)
        located = locate(services, recipe_id, stored.version, recipe, camera_id, robot)
        answer = located.answer()
        session.check()  # a Stop during the grab or the search ends the pick here
        k = next((i for i, c in enumerate(located.candidates) if c.reachable), None)
        if k is None:
            raise PickError(answer.get("reason") or
                            "no reachable pick: nothing found, or every pose is outside the envelope")
        best = answer["picks"][k]
        T_pick, T_app = located.candidates[k].T_pick, located.candidates[k].T_approach
        try:
            for T, why in ((T_app, "approach"), (T_pick, "pick"), (T_app, "retreat")):
                audited_move(services.store, who, robot, T, recipe.speed_m_s, f"pick {why}", session)
        except Exception as exc:
            halt_after_failure(robot, exc)
            raise
    answer["moved"] = True
    answer["picked"] = best
    return answer


CAPTURE_TOLERANCE_MM = 1.0
CAPTURE_TOLERANCE_DEG = 0.2


def _capture_pose(recipe: Recipe) -> NDArray[np.float64] | None:
    return None if recipe.capture_pose_ur is None else g.ur_pose_to_transform(list(recipe.capture_pose_ur))


def _off_pose(robot: RobotBase, T_capture: NDArray[np.float64]) -> str | None:
    """How far the robot is from ``T_capture`` ("12.3 mm, 0.5 deg"), or None when it is there."""
    T = robot.state().T_base_tool
    d_mm = float(np.linalg.norm(T[:3, 3] - T_capture[:3, 3])) * 1e3
    a_deg = math.degrees(g.rotation_angle(T[:3, :3].T @ T_capture[:3, :3]))
    if d_mm <= CAPTURE_TOLERANCE_MM and a_deg <= CAPTURE_TOLERANCE_DEG:
        return None
    return f"{d_mm:.1f} mm, {a_deg:.2f} deg"


