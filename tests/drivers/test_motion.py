"""The motion contract on the real-time virtual robot: Stop that stops, one owner, deadlines, faults.

The virtual robot moves in real time here (scale 1, the built-in scene's default), so a Stop,
a second mover or a deadline meets a move that is really under way. Waits are on events and
on the robot's own ``moving`` flag, never on a fixed sleep whose length decides the outcome.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration.geometry import ur_pose_to_transform
from drivers.base import (
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    MotionLimits,
    MotionRejected,
    RobotBase,
    RobotBusy,
    RobotState,
    RobotStopped,
)
from drivers.robot.sim import SimRobot, SimRobotSettings
from drivers.sim.scene import BUILTIN_SCENE
from drivers.sim.world import forget_worlds

LIMITS = MotionLimits((100.0, 800.0), (-400.0, 400.0), (2.0, 800.0), max_linear_speed_m_s=0.25)
HOME = ur_pose_to_transform([0.40, 0.0, 0.55, np.pi, 0.0, 0.0])
FAR = ur_pose_to_transform([0.40, 0.0, 0.35, np.pi, 0.0, 0.0])  # 200 mm below home


def _wait_for(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.005)


class _Mover:
    """Runs one robot call in a thread and keeps what it raised."""

    def __init__(self, fn: Callable[[], None]) -> None:
        self.error: BaseException | None = None
        self.done = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(fn,), daemon=True)
        self._thread.start()

    def _run(self, fn: Callable[[], None]) -> None:
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - the test inspects it
            self.error = exc
        finally:
            self.done.set()

    def join(self, timeout_s: float = 10.0) -> BaseException | None:
        assert self.done.wait(timeout_s), "the robot call did not return"
        return self.error


def _scene(tmp_path: Path, **robot: object) -> str:
    data = yaml.safe_load(BUILTIN_SCENE.read_text())
    data["robot"].update(robot)
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(data))
    return str(p)


@pytest.fixture
def robot() -> Iterator[SimRobot]:
    forget_worlds()
    r = SimRobot("robot0", SimRobotSettings(seed=1), LIMITS)
    with r:
        yield r
    forget_worlds()


def test_builtin_virtual_robot_moves_in_real_time(robot: SimRobot) -> None:
    assert robot.time_scale == 1.0
    t0 = time.monotonic()
    mover = _Mover(lambda: robot.move_linear(FAR, 0.25))  # 0.2 m at 0.25 m/s: 0.8 s
    _wait_for(lambda: robot.state().moving and robot.world.T_base_tool_true[2, 3] < 0.549)
    z_mm = robot.world.T_base_tool_true[2, 3] * 1000
    assert robot.state().moving and 350.0 < z_mm < 549.0  # on its way, seen between start and end
    assert mover.join() is None
    assert time.monotonic() - t0 >= 0.75
    assert not robot.state().moving
    assert np.allclose(robot.world.T_base_tool_true, FAR)


def test_stop_halts_mid_move_raises_and_latches_until_resume(robot: SimRobot) -> None:
    mover = _Mover(lambda: robot.move_linear(FAR, 0.1))  # 2 s
    _wait_for(lambda: robot.world.T_base_tool_true[2, 3] < 0.53)
    robot.stop(by="operator-1")
    err = mover.join()
    assert isinstance(err, RobotStopped), err
    z_stop = robot.world.T_base_tool_true[2, 3]
    assert 0.36 < z_stop < 0.53  # halted where it was, not at the target
    time.sleep(0.05)
    assert robot.world.T_base_tool_true[2, 3] == z_stop  # and it stays there
    assert robot.motion.status()["latched"] and robot.motion.status()["latched_by"] == "operator-1"
    with pytest.raises(RobotStopped, match="resume"):
        robot.move_linear(HOME, 0.25)
    assert robot.resume() is True
    robot.move_linear(ur_pose_to_transform([0.40, 0.0, z_stop + 0.01, np.pi, 0, 0]), 0.25)
    assert not robot.motion.latched


def test_a_pure_turn_takes_time_and_a_stop_meets_it_under_way(robot: SimRobot) -> None:
    """A turn about the tool axis moves no distance, yet it takes the turn at the scene's
    ``tool_turn_speed_deg_s`` (90 deg/s): 90 deg is 1 s, and a Stop halts it part way round."""
    turned = HOME @ ur_pose_to_transform([0, 0, 0, 0, 0, np.pi / 2])

    def yaw_deg() -> float:
        R = HOME[:3, :3].T @ robot.world.T_base_tool_true[:3, :3]
        return float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))

    t0 = time.monotonic()
    robot.move_linear(turned, 0.25)
    assert time.monotonic() - t0 >= 0.95
    assert abs(yaw_deg() - 90.0) < 1e-6
    mover = _Mover(lambda: robot.move_linear(HOME, 0.25))
    _wait_for(lambda: robot.state().moving and yaw_deg() < 80.0)
    robot.stop(by="op")
    assert isinstance(mover.join(), RobotStopped)
    assert 1.0 < yaw_deg() < 80.0  # halted part way round, not at the target
    assert robot.resume() is True


def test_stop_aborts_the_whole_sequence(robot: SimRobot) -> None:
    reached: list[str] = []

    def sequence() -> None:
        with robot.motion_session("pick", "pick of recipe 1") as s:
            for name, T in (("approach", FAR), ("pick", HOME), ("retreat", FAR)):
                robot.move_linear(T, 0.2, session=s)
                reached.append(name)

    mover = _Mover(sequence)
    _wait_for(lambda: robot.state().moving)
    robot.stop(by="op")
    assert isinstance(mover.join(), RobotStopped)
    assert reached == []  # the rest of the sequence never ran
    assert robot.motion.status()["owner"] is None  # the session ended with the sequence


def test_a_second_mover_is_refused_while_one_moves(robot: SimRobot) -> None:
    mover = _Mover(lambda: robot.move_linear(FAR, 0.2))
    _wait_for(lambda: robot.state().moving)
    with pytest.raises(RobotBusy, match="busy"):
        robot.move_linear(HOME, 0.2)
    with pytest.raises(RobotBusy):
        robot.motion.begin("someone", "routine intrinsics-capture")
    assert mover.join() is None
    assert np.allclose(robot.world.T_base_tool_true, FAR)  # the first move ended where it was sent


def test_a_session_owner_blocks_direct_moves_between_its_moves(robot: SimRobot) -> None:
    with robot.motion_session("routine", "routine handeye-capture") as s:
        with pytest.raises(RobotBusy):
            robot.move_linear(FAR, 0.25)
        robot.move_linear(ur_pose_to_transform([0.40, 0.0, 0.54, np.pi, 0, 0]), 0.25, session=s)
    with pytest.raises(RobotBusy, match="ended"):
        robot.move_linear(FAR, 0.25, session=s)  # a closed session moves nothing


@pytest.mark.parametrize("speed", [1e-6, 1e-300])
def test_a_speed_too_slow_to_finish_is_refused_with_the_minimum(robot: SimRobot, speed: float) -> None:
    with pytest.raises(MotionRejected, match=r"would take .* use at least 0.00333 m/s"):
        robot.move_linear(FAR, speed)
    assert np.allclose(robot.world.T_base_tool_true, HOME)


def test_an_upside_down_tool_is_refused() -> None:
    up = ur_pose_to_transform([0.40, 0.0, 0.005, 0.0, 0.0, 0.0])  # tool z pointing up
    with pytest.raises(MotionRejected, match="from pointing down"):
        LIMITS.check_pose(up)
    tilted = ur_pose_to_transform([0.40, 0.0, 0.3, np.pi - np.radians(30), 0.0, 0.0])
    LIMITS.check_pose(tilted)  # 30 deg off down: inside the default 60 deg cone


def test_a_late_move_is_stopped_at_its_deadline(tmp_path: Path) -> None:
    forget_worlds()
    limits = MotionLimits((100.0, 800.0), (-400.0, 400.0), (2.0, 800.0), max_linear_speed_m_s=0.25,
                          move_deadline_slack_s=0.2)
    # The virtual arm is three times slower than commanded: 0.2 m at 0.25 m/s is 0.8 s nominal, 2.4 s
    # in the sim; the deadline is 1.5 x 0.8 + 0.2 = 1.4 s.
    r = SimRobot("robot0", SimRobotSettings(seed=1, motion_time_scale=3.0), limits)
    with r:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="did not finish within 1.4 s"):
            r.move_linear(FAR, 0.25)
        elapsed = time.monotonic() - t0
        assert 1.3 < elapsed < 2.2  # stopped at the deadline, not at the end of the slow move
        assert r.world.T_base_tool_true[2, 3] > FAR[2, 3] + 0.01  # it did not arrive
        assert not r.motion.latched  # a deadline stop is not an operator's Stop
    forget_worlds()


def test_protective_stop_and_drop_off_raise_like_a_controller(tmp_path: Path) -> None:
    forget_worlds()
    scene = _scene(tmp_path, faults={"protective_stop_after_moves": 1, "drop_after_moves": 3})
    r = SimRobot("robot0", SimRobotSettings(scene=scene), LIMITS)
    with r:
        r.move_linear(ur_pose_to_transform([0.40, 0.0, 0.50, np.pi, 0, 0]), 0.25)
        with pytest.raises(DeviceOperationError, match="protective stop"):
            r.move_linear(FAR, 0.25)
        assert r.state().mode == "protective_stop"
        with pytest.raises(DeviceOperationError, match="protective stop"):
            r.move_linear(HOME, 0.25)
        r.unlock_protective_stop()
        r.move_linear(ur_pose_to_transform([0.40, 0.0, 0.45, np.pi, 0, 0]), 0.25)
        with pytest.raises(DeviceUnavailable, match="does not answer"):
            r.state()
    forget_worlds()


def test_kinematic_error_is_pose_dependent_and_deterministic_per_seed(tmp_path: Path) -> None:
    poses = [ur_pose_to_transform(p) for p in ([0.40, 0.0, 0.50, np.pi, 0, 0], [0.55, 0.2, 0.25, np.pi, 0.2, 0],
                                               [0.30, -0.25, 0.35, np.pi, -0.2, 0.3])]

    def errors(seed: int) -> np.ndarray:
        forget_worlds()
        scene = _scene(tmp_path, kinematic_error={"seed": seed, "link_sigma_mm": 0.5,
                                                  "joint_offset_sigma_deg": 0.05},
                       motion_time_scale=0.0, repeatability_mm=0.0, repeatability_deg=0.0)
        r = SimRobot("robot0", SimRobotSettings(scene=scene), LIMITS)
        out = []
        with r:
            for T in poses:
                r.move_linear(T, 0.25)
                assert np.allclose(r.state().T_base_tool, T, atol=1e-9)  # the controller reports its belief
                out.append((r.world.T_base_tool_true[:3, 3] - T[:3, 3]) * 1000)
        forget_worlds()
        return np.array(out)

    e7, e7b, e8 = errors(7), errors(7), errors(8)
    assert np.array_equal(e7, e7b)  # deterministic per seed
    norms = np.linalg.norm(e7, axis=1)
    assert np.all((norms > 0.05) & (norms < 10.0)), norms  # millimetres, not hundredths
    assert np.linalg.norm(e7[0] - e7[1]) > 0.05  # depends on the pose: not a constant offset
    assert not np.allclose(e7, e8)


class _StopFails(RobotBase):
    def __init__(self) -> None:
        super().__init__("r", LIMITS)

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass

    def state(self) -> RobotState:
        return RobotState(HOME, np.zeros(6), time.time())

    def _move_linear(self, T_base_tool: np.ndarray, speed_m_s: float) -> None:
        pass

    def _stop(self) -> None:
        raise DeviceUnavailable("controller gone")


def test_a_failing_stop_is_raised_and_the_latch_holds() -> None:
    r = _StopFails()
    with pytest.raises(DeviceUnavailable, match="controller gone"):
        r.stop(by="op")
    assert r.motion.latched
    with pytest.raises(RobotStopped):
        r.move_linear(FAR, 0.1)


def test_a_sequence_that_finds_its_controller_gone_latches_a_lone_move_does_not() -> None:
    """The controller is gone at a sequence's next move: a dropout mid-sequence, latched as a Stop
    latches. A lone move asked for while the controller is already gone is an outage: refused, no latch."""
    forget_worlds()
    r = SimRobot("robot0", SimRobotSettings(seed=1, motion_time_scale=0.0), LIMITS)
    with r:
        with r.motion_session("test", "a two-move sequence") as session:
            r.move_linear(HOME, 0.25, session=session)
            r.simulate_drop_off()
            with pytest.raises(DeviceUnavailable):
                r.move_linear(FAR, 0.25, session=session)
        status = r.motion.status()
        assert status["latched"] and status["latched_by"] == "controller", status
        assert "controller dropped out" in status["latched_reason"]
        assert r.resume() is True
        r.connect()  # the controller is back
        r.move_linear(FAR, 0.25)
        r.simulate_drop_off()
        with pytest.raises(DeviceUnavailable):
            r.move_linear(HOME, 0.25)
        assert not r.motion.latched
    forget_worlds()
