"""Pick guidance on the virtual cell: teach, move the part, find it, and pick it — against truth.

The calibrations are the virtual cell's true camera and hand-eye (stored and activated as any
calibration would be), so this measures the pick pipeline itself; the served end-to-end tests
run the same flow through calibrations the routines computed.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from cellctl.config import default_config_text
from cellctl.pick.flow import PickError, Recipe, fold_yaw, run_pick
from cellctl.pick.model import teach
from cellctl.services import Services
from drivers.base import RobotBusy
from drivers.sim.world import SimWorld, world_for
from tests.support.truth import calibrated_services

SEED = 11


@pytest.fixture()
def services(tmp_path: Path) -> Iterator[Services]:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path / "cell.db")}
    data["cameras"]["cam0"]["settings"]["seed"] = SEED
    data["robots"]["robot0"]["settings"]["seed"] = SEED
    data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.0  # the pick itself, not the travel, is tested
    with calibrated_services(data, SEED) as svc:
        yield svc


def part_pixel(world: SimWorld, x_mm: float, y_mm: float) -> tuple[float, float]:
    T_cam_base = g.invert(world.T_base_cam())
    uv = world.camera_model.project(g.transform_points(T_cam_base, [x_mm * 1e-3, y_mm * 1e-3, 0.0]))[0]
    return float(uv[0]), float(uv[1])


def teach_bracket(services: Services) -> Recipe:
    world = world_for(None, SEED)
    part = world.scene.parts[0]
    u, v = part_pixel(world, part.x_mm, part.y_mm)
    image = world.render()
    model = teach(image, (u - 100, v - 100, 200, 200), mode="shape", name="bracket")
    recipe = Recipe(name="bracket", models=[model.to_dict()], plane_z_mm=0.0, grasp_z_mm=5.0, approach_height_mm=40.0)
    services.store.save_recipe(1, "bracket", recipe.model_dump(mode="json"), "test")
    return recipe


def test_pick_pose_matches_truth_after_the_part_moved(services: Services) -> None:
    teach_bracket(services)
    world = world_for(None, SEED)
    part = world.scene.parts[0]
    before = run_pick(services, 1)
    assert before["picks"] and before["picks"][0]["part"] == "bracket"
    yaw0 = before["picks"][0]["base_yaw_deg"]
    p0 = before["picks"][0]["pick_pose"]
    assert math.hypot(p0["x_mm"] - part.x_mm, p0["y_mm"] - part.y_mm) < 0.3
    # The part is put down elsewhere, turned by 45 degrees.
    part.x_mm, part.y_mm, part.angle_deg = part.x_mm - 20.0, part.y_mm - 25.0, part.angle_deg + 45.0
    after = run_pick(services, 1)
    best = after["picks"][0]
    assert best["part"] == "bracket" and best["reachable"]
    p = best["pick_pose"]
    assert math.hypot(p["x_mm"] - part.x_mm, p["y_mm"] - part.y_mm) < 0.3
    assert abs(p["z_mm"] - 5.0) < 1e-6
    turn = (best["base_yaw_deg"] - yaw0 + 180) % 360 - 180
    assert abs(abs(turn) - 45.0) < 0.2
    assert best["uncertainty"]["sigma_mm"][0] > 0
    assert after["latency_ms"]["total"] > 0 and after["image_url"] == f"/frames/{after['frame_id']}.png"
    # The tool points down and the parallel gripper never turns more than 90 degrees from its yaw now.
    T = np.array(best["T_base_tool"])
    assert np.allclose(T[:3, 2], [0, 0, -1], atol=1e-9)
    assert abs(best["gripper_yaw_deg"]) <= 90.0 + 1e-9


def test_robot_picks_the_part(services: Services) -> None:
    teach_bracket(services)
    world = world_for(None, SEED)
    part = world.scene.parts[0]
    answer = run_pick(services, 1, move=True, who="engineer")
    assert answer["moved"]
    T_pick = np.array(answer["picked"]["T_base_tool"])
    assert math.hypot(T_pick[0, 3] * 1e3 - part.x_mm, T_pick[1, 3] * 1e3 - part.y_mm) < 0.3
    # The robot retreated straight up from the pick pose.
    T_now = world.T_base_tool_true
    assert np.allclose(T_now[:2, 3], T_pick[:2, 3], atol=1e-9)
    assert abs(T_now[2, 3] - T_pick[2, 3] - 0.040) < 1e-9
    moves = [a for a in services.store.audit_log(10, "robot.move")]
    assert [m.detail["why"] for m in moves[:3]] == ["pick retreat", "pick pick", "pick approach"]


def test_pose_outside_envelope_is_not_reachable_and_never_sent(services: Services) -> None:
    recipe = teach_bracket(services)
    low = recipe.model_copy(update={"grasp_z_mm": -50.0})  # below the table: outside z >= 2 mm
    services.store.save_recipe(2, "too low", low.model_dump(mode="json"), "test")
    world = world_for(None, SEED)
    before = world.T_base_tool_true
    answer = run_pick(services, 2)
    assert answer["picks"] and not answer["picks"][0]["reachable"]
    assert "outside the workspace envelope" in answer["picks"][0]["not_reachable_reason"]
    with pytest.raises(PickError, match="no reachable pick"):
        run_pick(services, 2, move=True)
    assert np.allclose(world.T_base_tool_true, before)


def test_fold_yaw_respects_gripper_symmetry() -> None:
    assert fold_yaw(math.radians(170), math.pi, 0.0) == pytest.approx(math.radians(-10))
    assert fold_yaw(math.radians(-100), math.pi, 0.0) == pytest.approx(math.radians(80))
    assert fold_yaw(math.radians(100), 2 * math.pi, 0.0) == pytest.approx(math.radians(100))
    assert fold_yaw(math.radians(44), math.pi / 2, 0.0) == pytest.approx(math.radians(44))
    assert fold_yaw(math.radians(46), math.pi / 2, 0.0) == pytest.approx(math.radians(-44))


def test_a_recipe_with_a_capture_pose_is_seen_from_there(services: Services) -> None:
    recipe = teach_bracket(services)
    world = world_for(None, SEED)
    home = g.transform_to_ur_pose(world.T_base_tool_true)
    with_pose = recipe.model_copy(update={"capture_pose_ur": tuple(float(v) for v in home)})
    services.store.save_recipe(3, "bracket from home", with_pose.model_dump(mode="json"), "test")
    robot = services.cell.robot("robot0").ensure_open()
    away = world.T_base_tool_true.copy()
    away[0, 3] += 0.03
    robot.move_linear(away, 0.25)
    with pytest.raises(PickError, match=r"30\.0 mm, 0\.00 deg from recipe 3's capture pose"):
        run_pick(services, 3)
    answer = run_pick(services, 3, move=True, who="engineer")  # goes back to the capture pose first
    assert answer["moved"] and answer["picks"][0]["part"] == "bracket"
    assert np.allclose(answer["capture_pose"]["x_mm"], home[0] * 1e3, atol=0.2)
    whys = [m.detail["why"] for m in services.store.audit_log(10, "robot.move")]
    assert whys[:4] == ["pick retreat", "pick pick", "pick approach", "pick: to the capture pose"]


def test_the_tool_centre_offset_puts_the_gripper_centre_on_the_part(services: Services) -> None:
    recipe = teach_bracket(services)
    part = world_for(None, SEED).scene.parts[0]
    plain = run_pick(services, 1)["picks"][0]
    offset = recipe.model_copy(update={"tool_centre_offset_mm": (12.0, -7.0)})
    services.store.save_recipe(4, "bracket, offset gripper", offset.model_dump(mode="json"), "test")
    best = run_pick(services, 4)["picks"][0]
    T_flange = np.array(best["T_base_tool"])
    # The feature sits at the flange plus the offset turned with the tool (tool x/y along base x/y at rz = 0).
    yaw = math.radians(best["gripper_yaw_deg"])
    c, s = math.cos(yaw), math.sin(yaw)
    feature_mm = T_flange[:2, 3] * 1e3 + np.array([c * 12.0 + s * 7.0, s * 12.0 - c * 7.0])
    assert math.hypot(feature_mm[0] - part.x_mm, feature_mm[1] - part.y_mm) < 0.3
    assert math.hypot(best["pick_pose"]["x_mm"] - plain["pick_pose"]["x_mm"],
                      best["pick_pose"]["y_mm"] - plain["pick_pose"]["y_mm"]) == pytest.approx(math.hypot(12, 7),
                                                                                                abs=0.05)


def test_the_recipe_carries_the_matchers_search_options(services: Services) -> None:
    recipe = teach_bracket(services)
    tuned = recipe.model_copy(update={"search": recipe.search.model_copy(update={
        "polarity": "use_polarity", "scale_range": (0.95, 1.05), "mirrored": True, "greediness": 0.5})})
    services.store.save_recipe(5, "bracket, tuned search", tuned.model_dump(mode="json"), "test")
    best = run_pick(services, 5)["picks"][0]
    assert best["part"] == "bracket" and not best["mirrored"] and abs(best["scale"] - 1.0) < 0.01
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="scale_range"):
        Recipe.model_validate({**tuned.model_dump(mode="json"), "search": {"scale_range": [1.2, 0.9]}})


def test_locating_through_a_camera_on_the_arm_holds_the_robot_still(services: Services) -> None:
    """POST /pick without move grabs a frame and reads the pose it was taken from: with the camera on the
    arm, another caller's move in between would pair them wrongly, so the locate holds the robot."""
    teach_bracket(services)
    robot = services.cell.robot("robot0").ensure_open()
    mover = robot.motion.begin("engineer", "another caller's move")
    try:
        with pytest.raises(RobotBusy):
            run_pick(services, 1)
    finally:
        robot.motion.end(mover)
    assert run_pick(services, 1)["picks"]  # free again: located as before
    assert robot.motion.status()["owner"] is None  # the hold ended with the locate
