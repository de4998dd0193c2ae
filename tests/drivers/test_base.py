"""The contract layer: the envelope and speed check that no adapter can bypass, the registry."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.geometry import ur_pose_to_transform
from drivers.base import MotionLimits, MotionRejected, RobotBase, RobotState
from drivers.registry import UnknownAdapter, adapter_class, kinds
from drivers.robot.sim import SimRobot, SimRobotSettings

LIMITS = MotionLimits((100.0, 800.0), (-400.0, 400.0), (50.0, 800.0), max_linear_speed_m_s=0.25)


class _RecordingRobot(RobotBase):
    """An adapter that records what reaches its hook: nothing may arrive unchecked."""

    def __init__(self) -> None:
        super().__init__("r", LIMITS)
        self.sent: list[np.ndarray] = []

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass

    def state(self) -> RobotState:
        return RobotState(np.eye(4), np.zeros(6), 0.0)

    def _move_linear(self, T_base_tool: np.ndarray, speed_m_s: float) -> None:
        self.sent.append(T_base_tool)

    def _stop(self) -> None:
        pass


@pytest.mark.parametrize(
    ("pose", "speed", "message"),
    [
        ([0.9, 0.0, 0.3, np.pi, 0, 0], 0.1, "x = 900.0 mm is outside the workspace envelope [100.0, 800.0] mm"),
        ([0.4, -0.5, 0.3, np.pi, 0, 0], 0.1, "y = -500.0 mm is outside"),
        ([0.4, 0.0, 0.01, np.pi, 0, 0], 0.1, "z = 10.0 mm is outside"),
        ([0.4, 0.0, 0.3, np.pi, 0, 0], 0.5, "linear speed 0.5 m/s is outside (0, 0.25] m/s"),
        ([0.4, 0.0, 0.3, np.pi, 0, 0], 0.0, "linear speed 0.0 m/s"),
        ([0.4, 0.0, 0.3, np.pi, 0, 0], float("nan"), "linear speed nan"),
    ],
)
def test_motion_outside_limits_is_rejected_before_the_adapter(pose: list[float], speed: float, message: str) -> None:
    robot = _RecordingRobot()
    with pytest.raises(MotionRejected) as err:
        robot.move_linear(ur_pose_to_transform(pose), speed)
    assert message in str(err.value)
    assert robot.sent == []


def test_motion_inside_limits_reaches_the_adapter() -> None:
    robot = _RecordingRobot()
    T = ur_pose_to_transform([0.4, 0.1, 0.3, np.pi, 0, 0])
    robot.move_linear(T, 0.1)
    assert len(robot.sent) == 1 and np.allclose(robot.sent[0], T)


def test_nonfinite_pose_rejected() -> None:
    robot = _RecordingRobot()
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(MotionRejected, match="finite"):
        robot.move_linear(T, 0.1)


def test_registry_knows_sim_and_replay_and_refuses_unknown() -> None:
    assert {"sim", "replay"} <= set(kinds("camera"))
    assert adapter_class("robot", "sim") is SimRobot
    with pytest.raises(UnknownAdapter, match="unknown robot kind 'warp'"):
        adapter_class("robot", "warp")


def test_sim_robot_moves_and_reports_with_repeatability_noise() -> None:
    from drivers.sim.world import forget_worlds

    forget_worlds()
    robot = SimRobot("robot0", SimRobotSettings(seed=3), LIMITS)
    with robot:
        target = ur_pose_to_transform([0.45, 0.05, 0.4, np.pi, 0.1, 0.0])
        robot.move_linear(target, 0.2)
        reported = robot.state().T_base_tool
        true = robot.world.T_base_tool_true
        assert np.allclose(true, target)
        err_mm = np.linalg.norm(reported[:3, 3] - target[:3, 3]) * 1000
        assert 0 < err_mm < 0.2  # 0.02 mm per axis, 1-sigma
        with pytest.raises(MotionRejected):
            robot.move_linear(ur_pose_to_transform([0.45, 0.05, 0.9, np.pi, 0, 0]), 0.2)
        assert np.allclose(robot.world.T_base_tool_true, target)  # refused move changed nothing
    robot.close()  # closing twice is safe
