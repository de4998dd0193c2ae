"""The virtual production cell keeps its parts, gripper and arm across a restart (the sim robot's
``state_file``): a new world of the same scene on the same file finds a held part still held with the
arm where it stopped, and a part put down where it lies; another scene's file is not taken."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivers.base import MotionLimits
from drivers.io.sim_gripper import SimGripper, SimGripperSettings
from drivers.robot.sim import SimRobot, SimRobotSettings
from drivers.sim import world as world_module
from tests.drivers.test_sim_gripper import parts, scene_file, tool_over

LIMITS = MotionLimits(x_mm=(100, 800), y_mm=(-500, 500), z_mm=(1, 800), max_linear_speed_m_s=1.0)


def _start(scene: Path, state: Path) -> tuple[SimRobot, SimGripper]:
    world_module._WORLDS.pop((str(scene.resolve()), 1), None)  # a new process: a new world
    robot = SimRobot("robot0", SimRobotSettings(scene=str(scene), seed=1, motion_time_scale=0.0,
                                                state_file=str(state)), LIMITS)
    gripper = SimGripper("gripper0", SimGripperSettings(scene=str(scene), seed=1, time_scale=0.0))
    robot.connect()
    gripper.open()
    return robot, gripper


def test_parts_gripper_and_arm_are_kept_across_a_restart(tmp_path: Path) -> None:
    scene, state = scene_file(tmp_path), tmp_path / "data" / "sim" / "cell-robot0.json"
    robot, gripper = _start(scene, state)
    fresh = parts(scene)
    part0, part1 = np.array(fresh[0]["T_base_part"]), np.array(fresh[1]["T_base_part"])
    robot.move_linear(tool_over(part1), 0.5)
    gripper.close_gripper()
    robot.move_linear(tool_over(part1, dz_mm=40, dx_mm=-60), 0.5)
    gripper.open_gripper()  # part 1 put down 60 mm from where it lay
    robot.move_linear(tool_over(part0), 0.5)
    assert gripper.close_gripper()["object_detected"]
    robot.move_linear(tool_over(part0, dz_mm=50), 0.5)
    before, T_tool = parts(scene), robot.world.T_base_tool_true
    assert [p["state"] for p in before[:2]] == ["held", "in_area"] and state.is_file()
    gripper.close()
    robot.close()

    robot, gripper = _start(scene, state)  # the service restarted
    after = parts(scene)
    assert [(p["id"], p["state"]) for p in after] == [(p["id"], p["state"]) for p in before]
    for a, b in zip(after, before, strict=True):
        assert np.allclose(a["T_base_part"], b["T_base_part"], atol=1e-9)
    assert np.allclose(robot.world.T_base_tool_true, T_tool)
    assert gripper.status()["object_detected"]  # still closed on part 0
    gripper.open_gripper()
    assert parts(scene)[0]["state"] == "in_area"
    gripper.close()
    robot.close()

    (tmp_path / "other").mkdir()
    other = scene_file(tmp_path / "other", scatter={"count": 3, "seed": 9})
    world_module._WORLDS.pop((str(other.resolve()), 1), None)
    world = world_module.world_for(str(other), 1)
    world.keep_state_in(state)  # another scatter: the kept file is not this scene's, it starts afresh
    assert [p["state"] for p in world.truth()["parts"]] == ["in_area"] * 3


def test_an_empty_state_file_keeps_nothing(tmp_path: Path) -> None:
    scene = scene_file(tmp_path)
    world_module._WORLDS.pop((str(scene.resolve()), 1), None)
    robot = SimRobot("robot0", SimRobotSettings(scene=str(scene), seed=1, motion_time_scale=0.0, state_file=""),
                     LIMITS)
    robot.connect()
    robot.move_linear(tool_over(np.array(parts(scene)[0]["T_base_part"]), dz_mm=30), 0.5)
    robot.close()
    assert not list(tmp_path.rglob("*.json"))
