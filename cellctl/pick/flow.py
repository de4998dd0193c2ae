"""The pick flow: grab, locate the recipe's parts, convert each match to a gripper pose, check it.

Every pose — pick and approach — is checked against the robot's envelope; a pose outside it is
reported ``reachable: false`` and never sent. The conversion of a match to a pose is
``cellctl.pick.pose``; the recipe is ``cellctl.pick.recipe``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl import metrics
from cellctl.arm_view import arm_view
from cellctl.mapping import active_mapping, npoint_pose_check
from cellctl.motion import audited_move, halt_after_failure
from cellctl.pick.frames import match_contours
from cellctl.pick.pose import fold_yaw, pick_pose, pose_json
from cellctl.pick.recipe import PickError, Recipe, SearchSettings
from cellctl.services import Services
from drivers.base import MotionRejected, RobotBase
from vision.recognize import recognize
from vision.types import SearchParams

__all__ = ["PickError", "Recipe", "SearchSettings", "fold_yaw", "pick_pose", "pose_json", "run_pick"]


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
        if not active_mapping(services, _camera_of(services, recipe, camera_id), robot_id, recipe.calibration,
                              recipe.plane_z_mm is not None).camera_on_arm:
            return _locate(services, recipe_id, stored.version, recipe, camera_id, robot)
        # A camera on the arm measures only while the arm stands still: hold it (RobotBusy while another
        # caller moves it), so the frame and the pose read with it belong together.
        still = robot.motion.begin(who, f"pick of recipe {recipe_id}: locating", still=True)
        try:
            return _locate(services, recipe_id, stored.version, recipe, camera_id, robot)
        finally:
            robot.motion.end(still)
    with robot.motion_session(who, f"pick of recipe {recipe_id}") as session:
        T_capture = _capture_pose(recipe)
        if T_capture is not None and _off_pose(robot, T_capture) is not None:
            audited_move(services.store, who, robot, T_capture, recipe.speed_m_s, "pick: to the capture pose", session)
        answer = _locate(services, recipe_id, stored.version, recipe, camera_id, robot)
        session.check()  # a Stop during the grab or the search ends the pick here
        best = next((p for p in answer["picks"] if p["reachable"]), None)
        if best is None:
            raise PickError(answer.get("reason") or
                            "no reachable pick: nothing found, or every pose is outside the envelope")
        T_pick = np.array(best["T_base_tool"])
        T_app = T_pick.copy()
        T_app[2, 3] += recipe.approach_height_mm * 1e-3
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


def _camera_of(services: Services, recipe: Recipe, camera_id: str | None) -> str:
    """The camera a pick looks through: the request's, else the recipe's, else the config's calibration camera."""
    return camera_id or recipe.camera_id or services.config.calibration.camera


def _locate(services: Services, recipe_id: int, version: int, recipe: Recipe, camera_id: str | None,
            robot: RobotBase) -> dict[str, Any]:
    t0 = time.perf_counter()
    cam_id = _camera_of(services, recipe, camera_id)
    robot_id = robot.robot_id
    models = recipe.part_models()
    mapping = active_mapping(services, cam_id, robot_id, recipe.calibration, recipe.plane_z_mm is not None)
    T_capture = robot.state().T_base_tool
    problem = npoint_pose_check(mapping, T_capture)
    if problem:
        raise PickError(problem)
    frame = services.cell.camera(cam_id).ensure_open().grab(timeout_s=5.0)
    t_grab = time.perf_counter()
    size = frame.size
    for m in models:
        if tuple(m.image_size) != size:
            raise PickError(f"part model {m.name} was taught on {m.image_size[0]}x{m.image_size[1]} images; "
                            f"camera {cam_id} delivers {size[0]}x{size[1]}: teach the part on this camera")
    sp = recipe.search
    search = SearchParams(min_score=sp.min_score, max_count=sp.max_count, angle_start_deg=sp.angle_start_deg,
                          angle_extent_deg=sp.angle_extent_deg, roi=sp.roi, timeout_s=sp.timeout_s,
                          polarity=sp.polarity, greediness=sp.greediness, scale_min=sp.scale_range[0],
                          scale_max=sp.scale_range[1], mirrored=sp.mirrored, max_overlap=sp.max_overlap,
                          min_surround=sp.min_surround)
    found = recognize(models, frame.pixels, search)
    t_find = time.perf_counter()
    current_yaw = math.atan2(T_capture[1, 0], T_capture[0, 0])
    # A fixed camera sees the arm (and the plate it may carry) where it stood at the grab: a match there is
    # the arm's, not a part (cellctl.arm_view).
    arm = arm_view(mapping, T_capture, services.config)
    matches = [r for r in found.matches if arm is None or not arm.covers(r.u_px, r.v_px)]
    picks = []
    for r in matches[: sp.max_count]:
        pp = pick_pose(mapping, recipe, r.u_px, r.v_px, r.angle_deg, T_capture, current_yaw, r.sigma_angle_deg)
        reason = None
        try:
            robot.limits.check_pose(pp["T_pick"])
            robot.limits.check_pose(pp["T_approach"])
        except MotionRejected as exc:
            reason = str(exc)
        picks.append({**r.as_dict(), "pick_pose": pose_json(pp["T_pick"]),
                      "approach_pose": pose_json(pp["T_approach"]), "T_base_tool": pp["T_pick"].tolist(),
                      "part_yaw_deg": pp["part_yaw_deg"], "base_yaw_deg": pp["base_yaw_deg"],
                      "gripper_yaw_deg": pp["gripper_yaw_deg"],
                      "uncertainty": {"sigma_mm": pp["sigma_mm"], "sigma_yaw_deg": pp["sigma_yaw_deg"]},
                      "reachable": reason is None, "not_reachable_reason": reason})
    reason = found.reason()
    frame_id = services.frames.add(frame.pixels, picks, match_contours(models, picks), reason)
    t_done = time.perf_counter()
    metrics.observe_pick(t_done - t0, [p["score"] for p in picks], source=services)
    answer: dict[str, Any] = {
        "recipe_id": recipe_id, "recipe_version": version, "camera_id": cam_id, "robot_id": robot_id,
        "frame_id": frame_id, "image_url": f"/frames/{frame_id}.png", "timed_out": found.timed_out,
        "calibration": {"kind": mapping.kind, "id": mapping.calibration_id},
        "capture_pose": pose_json(T_capture), "picks": picks, "reason": reason,
        "rejected": [x.as_dict() for x in found.rejected],
        "latency_ms": {"grab": (t_grab - t0) * 1e3, "find": (t_find - t_grab) * 1e3,
                       "total": (t_done - t0) * 1e3},
        "moved": False,
        "arm_in_view": arm.what if arm is not None and arm.share_of(sp.roi) > 0 else None,
    }
    return answer
