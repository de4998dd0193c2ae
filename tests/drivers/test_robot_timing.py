"""What a planner asks a robot about its own motion (``RobotBase.linear_move_s``, ``tool_turn_speed_deg_s``,
``tracking_report``): the base's defaults, and the sim arm timing its moves with the very function it answers
(a belt run's meeting plan is then never optimistic about the motion itself)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import numpy as np
import pytest

from calibration.geometry import ur_pose_to_transform
from drivers.base import MotionLimits, RobotBase
from drivers.robot.sim import STEP_S, SimRobot, SimRobotSettings
from drivers.sim.world import forget_worlds

LIMITS = MotionLimits((100.0, 800.0), (-400.0, 400.0), (2.0, 800.0), max_linear_speed_m_s=1.0)
HOME = ur_pose_to_transform([0.40, 0.0, 0.55, np.pi, 0, 0])


class _Bare(RobotBase):
    """An adapter that says nothing of its own motion."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def state(self):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    def _move_linear(self, T_base_tool: np.ndarray, speed_m_s: float) -> None: ...

    def _stop(self) -> None: ...


def test_the_bases_defaults_say_a_ramped_move_a_90_deg_s_turn_and_no_tracking_report() -> None:
    r = _Bare("bare", LIMITS)
    far = HOME.copy()
    far[0, 3] += 0.3
    assert r.linear_move_s(HOME, far, 1.0, 2.0) == pytest.approx(0.3 + 0.5)  # d / v + v / a
    turned = HOME @ ur_pose_to_transform([0, 0, 0, 0, 0, math.pi / 2])
    assert r.tool_turn_speed_deg_s() == 90.0 and r.linear_move_s(HOME, turned, 1.0) == pytest.approx(1.0)
    assert r.tracking_report() is None


@pytest.fixture
def robot() -> Iterator[SimRobot]:
    forget_worlds()
    r = SimRobot("robot0", SimRobotSettings(seed=1), LIMITS)
    with r:
        r.move_linear(HOME, 1.0)
        yield r
    forget_worlds()


def test_the_sim_arm_takes_the_time_it_says_a_move_takes(robot: SimRobot) -> None:
    """A travel and a turn-bound move each take what ``linear_move_s`` says (less one update step at most;
    the host's delays on top are a planner's lead): never longer than said by more than the host's delay."""
    far = HOME.copy()
    far[0, 3] += 0.3
    turned = far @ ur_pose_to_transform([0, 0, 0, 0, 0, math.radians(60)])
    for T_to, speed in ((far, 1.0), (turned, 1.0)):
        T_from = robot.world.T_base_tool_commanded
        said = robot.linear_move_s(T_from, T_to, speed)
        t0 = time.monotonic()
        robot.move_linear(T_to, speed)
        took = time.monotonic() - t0
        assert said - STEP_S - 0.005 <= took <= said + 0.25, (said, took)
    assert robot.linear_move_s(far, turned, 1.0) == pytest.approx(60.0 / robot.tool_turn_speed_deg_s() + STEP_S)
    assert robot.tracking_report() is None
