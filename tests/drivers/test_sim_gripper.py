"""The sim gripper on the production scene: it holds the part it closes on, carries it, lets it go.

The arm is the real sim robot adapter (its checked moves), the gripper the ``sim_gripper`` adapter,
both on one shared world; truth is the scene's.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from drivers.base import MotionLimits
from drivers.io.sim_gripper import SimGripper, SimGripperSettings
from drivers.robot.sim import SimRobot, SimRobotSettings
from drivers.sim import world as world_module
from drivers.sim.production import yaw_of
from drivers.sim.scene import BUILTIN_SCENES

LIMITS = MotionLimits(x_mm=(100, 800), y_mm=(-500, 500), z_mm=(1, 800), max_linear_speed_m_s=1.0)


def scene_file(tmp: Path, **production: Any) -> Path:
    data = yaml.safe_load(BUILTIN_SCENES["production"].read_text())
    for key, value in production.items():
        if isinstance(value, dict):
            data["production"].setdefault(key, {}).update(value)
        else:
            data["production"][key] = value
    path = tmp / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture()
def cell(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[SimRobot, SimGripper, Path]]:
    options = getattr(request, "param", {})
    scene = scene_file(tmp_path, **options)
    world_module._WORLDS.pop((str(scene.resolve()), 1), None)
    robot = SimRobot("robot0", SimRobotSettings(scene=str(scene), seed=1, motion_time_scale=0.0), LIMITS)
    gripper = SimGripper("gripper0", SimGripperSettings(scene=str(scene), seed=1, time_scale=0.0))
    robot.connect()
    gripper.open()
    yield robot, gripper, scene
    gripper.close()
    robot.close()


def tool_over(T_base_part: np.ndarray, dz_mm: float = 0.0, dyaw_deg: float = 0.0, dx_mm: float = 0.0) -> np.ndarray:
    yaw = yaw_of(T_base_part) + math.radians(dyaw_deg)
    R = g.rotvec_to_matrix([0.0, 0.0, yaw]) @ g.rotvec_to_matrix([math.pi, 0.0, 0.0])
    p = T_base_part[:3, 3] + np.array([dx_mm, 0.0, dz_mm]) * 1e-3
    return g.make_transform(R, p)


def parts(scene: Path) -> list[dict[str, Any]]:
    truth: list[dict[str, Any]] = world_module.world_for(str(scene), 1).truth()["parts"]
    return truth


def test_a_part_is_held_carried_and_put_down_where_the_gripper_opens(
        cell: tuple[SimRobot, SimGripper, Path]) -> None:
    robot, gripper, scene = cell
    part0 = np.array(parts(scene)[0]["T_base_part"])
    robot.move_linear(tool_over(part0, dz_mm=40), 0.5)
    assert gripper.open_gripper()["width_mm"] == pytest.approx(85.0)
    robot.move_linear(tool_over(part0, dyaw_deg=180.0), 0.5)  # the fingers are symmetric: turned 180 deg holds too
    status = gripper.close_gripper()
    assert status["object_detected"] and status["holding"] == 0 and status["width_mm"] == pytest.approx(30.0)
    assert parts(scene)[0]["state"] == "held"
    slot = np.array(world_module.world_for(str(scene), 1).truth()["place_grid"]["origin_ur"])
    T_slot = g.ur_pose_to_transform(slot)
    robot.move_linear(tool_over(part0, dz_mm=40, dyaw_deg=180.0), 0.5)
    carried = np.array(parts(scene)[0]["T_base_part"])
    assert carried[2, 3] == pytest.approx(part0[2, 3] + 0.04, abs=1e-4)  # it went up with the tool
    # Turn the part to the slot's yaw (0) and put it down there.
    T_place = T_slot @ g.invert(carried) @ robot.world.T_base_tool_true
    robot.move_linear(T_place, 0.5)
    assert not gripper.open_gripper()["object_detected"]
    after = parts(scene)[0]
    assert after["state"] == "placed"
    rot, trans = g.transform_error(np.array(after["T_base_part"]), T_slot)
    assert trans * 1e3 < 0.2 and math.degrees(rot) < 0.1, (trans, rot)
    assert after["roi_px"] is None  # the place area is out of the camera's view


@pytest.mark.parametrize("offset", [{"dx_mm": 4.0}, {"dyaw_deg": 10.0}, {"dz_mm": 8.0}])
def test_a_close_beside_the_tolerance_holds_nothing(cell: tuple[SimRobot, SimGripper, Path],
                                                    offset: dict[str, float]) -> None:
    robot, gripper, scene = cell
    part0 = np.array(parts(scene)[0]["T_base_part"])
    robot.move_linear(tool_over(part0, **offset), 0.5)
    status = gripper.close_gripper()
    assert not status["object_detected"] and status["width_mm"] == 0.0, gripper.last_reason
    assert parts(scene)[0]["state"] == "in_area"
    assert gripper.last_reason


@pytest.mark.parametrize("cell", [{"gripper": {"fail_probability": 1.0}}], indirect=True)
def test_a_grip_failure_closes_empty(cell: tuple[SimRobot, SimGripper, Path]) -> None:
    robot, gripper, scene = cell
    part0 = np.array(parts(scene)[0]["T_base_part"])
    robot.move_linear(tool_over(part0), 0.5)
    assert not gripper.close_gripper()["object_detected"]
    assert "slipped" in gripper.last_reason


@pytest.mark.parametrize("cell", [{"gripper": {"slip_accel_m_s2": 3.0}}], indirect=True)
def test_a_held_part_slips_at_a_hard_start(cell: tuple[SimRobot, SimGripper, Path]) -> None:
    robot, gripper, scene = cell
    part0 = np.array(parts(scene)[0]["T_base_part"])
    robot.move_linear(tool_over(part0), 0.5)
    assert gripper.close_gripper()["object_detected"]
    robot.move_linear(tool_over(part0, dz_mm=20), 0.2)  # 0.2 m/s in 0.1 s: 2 m/s^2, held
    assert parts(scene)[0]["state"] == "held"
    robot.move_linear(tool_over(part0, dz_mm=60), 0.5)  # 5 m/s^2: it slips and falls
    assert parts(scene)[0]["state"] == "dropped" and not gripper.read_input(0)


def test_the_scatter_is_seeded_touching_turned_and_reaches_the_area_edge(tmp_path: Path) -> None:
    scene = scene_file(tmp_path, scatter={"count": 16})
    from drivers.sim.scene import load_scene
    from drivers.sim.world import SimWorld

    a = SimWorld(load_scene(scene)).production
    b = SimWorld(load_scene(scene)).production
    assert a is not None and b is not None
    poses = [p.T_base_part for p in a.parts]
    assert len(poses) == 16
    assert all(np.array_equal(p.T_base_part, q.T_base_part) for p, q in zip(a.parts, b.parts, strict=True))
    yaws = np.degrees([yaw_of(T) for T in poses])
    assert np.ptp(yaws) > 180  # turned every way
    area = a.spec.pick_area
    corners = [a.outline_in_base(T)[:, :2] * 1e3 for T in poses]
    edge_gap = min(min(c[:, 0].min() - area.x_mm[0], area.x_mm[1] - c[:, 0].max(),
                       c[:, 1].min() - area.y_mm[0], area.y_mm[1] - c[:, 1].max()) for c in corners)
    assert -1e-6 <= edge_gap < 3.0  # inside the area, one against its edge
    centre_gaps = [np.linalg.norm(p[:2, 3] - q[:2, 3]) * 1e3 for i, p in enumerate(poses) for q in poses[i + 1:]]
    assert min(centre_gaps) < 2 * a.spec.part_radius_mm()  # neighbours nearer than their circles allow: touching
