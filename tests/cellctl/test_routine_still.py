"""A routine's shot is taken while it owns the robot: ``routines.common.robot_still`` and ``capture``.

On the real-time virtual robot and camera of the built-in scene (one shared world), with a real
job context: another caller's session refuses the shot, the routine's own session lets it
through, a free or latched robot is held still for the shot (nothing moves it meanwhile, not even
after a resume) and free again after it.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from calibration.geometry import ur_pose_to_transform
from calibration.targets import target_from_dict
from cellctl.jobs import Job, JobContext
from cellctl.routines.common import capture, robot_still
from drivers.base import MotionLimits, MotionSession, RobotBusy, RobotStopped
from drivers.camera.sim import SimCamera, SimCameraSettings
from drivers.robot.sim import SimRobot, SimRobotSettings
from drivers.sim.world import forget_worlds

LIMITS = MotionLimits((100.0, 800.0), (-400.0, 400.0), (2.0, 800.0), max_linear_speed_m_s=0.25)
PLATE = target_from_dict({"type": "circle_plate", "cols": 7, "rows": 7, "pitch_mm": 20.0, "diameter_mm": 10.0})


@pytest.fixture
def robot() -> Iterator[SimRobot]:
    forget_worlds()
    r = SimRobot("robot0", SimRobotSettings(seed=1), LIMITS)
    with r:
        yield r
    forget_worlds()


def _ctx(motion: MotionSession | None = None) -> JobContext:
    return JobContext(Job(id="job1", name="verify", started_by="operator-1", params={}), motion)


AWAY = ur_pose_to_transform([0.42, 0.0, 0.5, np.pi, 0.0, 0.0])


def test_a_free_robot_is_held_still_for_the_shot_and_free_after_it(robot: SimRobot) -> None:
    with robot_still(_ctx(), robot, "verify: shot"):
        owner = robot.motion.status()["owner"]
        assert owner == {"who": "operator-1", "what": "routine verify: shot", "since_s": owner["since_s"],
                         "still": True}
        with pytest.raises(RobotBusy, match="routine verify: shot"):
            robot.move_linear(AWAY, 0.1)
    assert robot.motion.status()["owner"] is None


def test_another_callers_session_refuses_the_shot(robot: SimRobot) -> None:
    with robot.motion_session("engineer-1", "a move") as theirs:
        with pytest.raises(RobotBusy, match="a move"), robot_still(_ctx(), robot, "verify: shot"):
            pytest.fail("the shot ran while another caller owned the robot")
        assert robot.motion.is_current(theirs)  # their session is untouched


def test_a_latched_robot_may_be_held_and_a_resume_meanwhile_does_not_free_it(robot: SimRobot) -> None:
    """A latched robot stands still: the shot is taken; an engineer's resume during it lets nothing move it."""
    robot.stop(by="operator-2")
    with robot_still(_ctx(), robot, "verify: shot"):
        assert robot.resume("engineer-1")
        with pytest.raises(RobotBusy, match="holds it still"):
            robot.move_linear(AWAY, 0.1)
        robot.stop(by="operator-2")  # a Stop during the shot latches; it does not abort the holder
    with pytest.raises(RobotStopped, match="operator-2"):
        robot.move_linear(AWAY, 0.1)
    assert robot.motion.status()["owner"] is None


def test_the_holders_session_cannot_move_the_robot(robot: SimRobot) -> None:
    held = robot.motion.begin("operator-1", "routine verify", still=True)
    try:
        with pytest.raises(RobotBusy, match="does not own"):
            robot.move_linear(AWAY, 0.1, session=held)
        with robot_still(_ctx(held), robot, "verify: shot"):  # the routine's own hold lets its shot through
            assert robot.motion.holds(held)
    finally:
        robot.motion.end(held)


def test_the_routines_own_session_lets_the_shot_through(robot: SimRobot) -> None:
    session = robot.motion.begin("engineer-1", "routine handeye-capture")
    try:
        with robot_still(_ctx(session), robot, "handeye-capture: shot"):
            assert robot.motion.is_current(session)
    finally:
        robot.motion.end(session)


def test_a_capture_is_refused_while_another_caller_moves_the_robot_and_taken_once_it_arrived(robot: SimRobot) -> None:
    cam = SimCamera("cam0", SimCameraSettings(seed=1))
    with cam:
        moving = threading.Event()
        done = threading.Event()
        target = ur_pose_to_transform([0.40, 0.0, 0.50, np.pi, 0.0, 0.0])  # 50 mm at 0.1 m/s: 0.5 s

        def move() -> None:
            with robot.motion_session("engineer-1", "a move") as s:
                moving.set()
                robot.move_linear(target, 0.1, session=s)
            done.set()

        t = threading.Thread(target=move, daemon=True)
        t.start()
        assert moving.wait(5.0)
        with pytest.raises(RobotBusy, match="a move"):
            capture(cam, robot, PLATE, "verify", _ctx())
        t.join(10.0)
        assert done.is_set()
        shot = capture(cam, robot, PLATE, "verify", _ctx())
        assert shot.T_base_tool is not None and np.allclose(shot.T_base_tool[:3, 3], target[:3, 3], atol=1e-4)
        assert shot.detection.found
