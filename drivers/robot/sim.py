"""Simulated robot (``kind: sim``): an arm of the virtual cell (``drivers/sim/``), as strict as a real one.

- Moves take real time: distance / speed, or the turn at the scene's ``tool_turn_speed_deg_s`` when
  that is longer, times the scene's ``motion_time_scale`` (1 by default). The tool travels the
  straight line (position linear, orientation by slerp) and the camera sees it on the way;
  ``state().moving`` is true meanwhile.
- ``_stop`` halts the tool where it is, and the interrupted move raises ``DeviceOperationError``
  like the UR adapter (``RobotBase`` turns it into ``RobotStopped`` for the caller).
- Faults of the scene (``robot.faults``): the operator's speed slider below 1 (every move slower than the
  robot's own timing says), a protective stop halfway through a move (the move
  raises, moves are refused until ``unlock_protective_stop``), and a controller that drops off the
  network (state and moves raise ``DeviceUnavailable`` until reconnected).
- A conveyor scene's arm tracks the belt (``start_tracking``: ``drivers.sim.conveyor.BeltTracker``);
  a Stop ends tracking at once.
- With ``robot.kinematic_error`` the true pose is the perturbed arm's (``drivers.sim.kinematics``);
  the reported pose stays the controller's belief with repeatability noise.

The motion checks, the motion owner and the Stop latch live in ``RobotBase``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation, Slerp

from drivers.base import DeviceOperationError, DeviceUnavailable, MotionLimits, MotionRejected, RobotBase, RobotState
from drivers.health import DeviceHealth
from drivers.robot_base import DEFAULT_ACCEL_M_S2, turn_deg
from drivers.sim.kinematics import OutOfReach
from drivers.sim.world import SimWorld, world_for

STEP_S = 0.01
"""How often a moving tool's pose is updated (s)."""


class SimRobotSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene: str | None = None
    """Scene file path; empty for the built-in virtual cell (must match the sim camera's)."""
    seed: int | None = Field(None, ge=0)
    motion_time_scale: float | None = Field(None, ge=0, le=10)
    """Overrides the scene's ``robot.motion_time_scale`` (1: real time; 0: instantaneous moves)."""
    state_file: str | None = None
    """Where a production scene's world keeps its parts, gripper and arm pose across a restart
    (``SimWorld.keep_state_in``); ``cellctl serve`` sets ``<data dir>/sim/<cell_id>-<robot_id>.json`` when
    None; "": nothing is kept (a fresh scene at every start)."""


class SimRobot(RobotBase):
    """A robot arm that exists only in the virtual cell."""

    Settings = SimRobotSettings

    def __init__(self, robot_id: str, settings: SimRobotSettings, limits: MotionLimits) -> None:
        super().__init__(robot_id, limits)
        self._settings = settings
        self._world: SimWorld | None = None
        self._halt = threading.Event()
        self._moving = False
        self._moves = 0
        self._protective_stop = False
        self._dropped = False

    @property
    def world(self) -> SimWorld:
        if self._world is None:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected; connect() it first")
        if self._dropped:
            raise DeviceUnavailable(f"robot {self.robot_id}: the controller does not answer (simulated drop-off)")
        return self._world

    @property
    def time_scale(self) -> float:
        s = self._settings.motion_time_scale
        return self.world.scene.robot.motion_time_scale if s is None else s

    def connect(self) -> None:
        self._world = world_for(self._settings.scene, self._settings.seed)
        if self._settings.state_file:
            self._world.keep_state_in(self._settings.state_file)
        self._dropped = False
        self._moves = 0

    def close(self) -> None:
        self._halt.set()
        self._world = None

    def health(self) -> DeviceHealth:
        if self._world is None:
            return DeviceHealth(available=False, reason="not connected")
        if self._dropped:
            return DeviceHealth(available=False, reason="the controller does not answer (simulated drop-off)")
        return DeviceHealth(available=True)

    def state(self) -> RobotState:
        world = self.world
        return RobotState(
            T_base_tool=world.T_base_tool_reported(),
            joints_rad=world.joints_rad,
            timestamp_s=time.time(),
            moving=self._moving,
            mode="protective_stop" if self._protective_stop else "running",
            metadata={"simulated": True, "safety_mode": "protective_stop" if self._protective_stop else "normal"},
        )

    # -- faults -----------------------------------------------------------------------------------
    def simulate_protective_stop(self) -> None:
        """Like a collision: halt now; moves are refused until ``unlock_protective_stop``."""
        self._protective_stop = True
        self._halt.set()

    def unlock_protective_stop(self) -> None:
        self._protective_stop = False

    def simulate_drop_off(self) -> None:
        """The controller vanishes from the network (until the next ``connect``)."""
        self._dropped = True
        self._halt.set()

    # -- motion -----------------------------------------------------------------------------------
    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        world = self.world
        if self._protective_stop:
            raise DeviceOperationError(f"robot {self.robot_id} is in a protective stop; inspect the cell, "
                                       "then unlock the protective stop before moving")
        try:
            joints, T_true_end = world.true_pose_for(T_base_tool)
        except OutOfReach as exc:
            raise MotionRejected(f"robot {self.robot_id}: {exc}") from exc
        self._halt.clear()
        faults = world.scene.robot.faults
        if not world.tracker.tracking:
            world.settle_tracking()
        world.move_started(speed_m_s)
        self._moves += 1
        protective_halfway = (faults.protective_stop_after_moves is not None
                              and self._moves == faults.protective_stop_after_moves + 1)
        duration_s = self._profile_s(world.T_base_tool_commanded, T_base_tool, speed_m_s) / faults.speed_slider
        if duration_s > 0 or protective_halfway:
            self._travel(world, T_base_tool, T_true_end, max(duration_s, STEP_S), protective_halfway)
        world.place_tool(T_base_tool, T_true_end, joints)
        if faults.drop_after_moves is not None and self._moves >= faults.drop_after_moves:
            self._dropped = True

    def tool_turn_speed_deg_s(self) -> float:
        """The scene's ``robot.tool_turn_speed_deg_s`` (before the motion time scale)."""
        return float(self.world.scene.robot.tool_turn_speed_deg_s)

    def _profile_s(self, T_from: NDArray[np.float64], T_to: NDArray[np.float64], speed_m_s: float) -> float:
        """The move's duration: the distance at ``speed_m_s``, or the turn at the scene's turn rate when that is
        longer, times the motion time scale (no ramps: the virtual arm starts and stops at once)."""
        return self.time_scale * max(float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3])) / speed_m_s,
                                     turn_deg(T_from, T_to) / self.tool_turn_speed_deg_s())

    def linear_move_s(self, T_from: NDArray[np.float64], T_to: NDArray[np.float64], speed_m_s: float,
                      accel_m_s2: float = DEFAULT_ACCEL_M_S2) -> float:
        """The move's duration as ``_move_linear`` times it (``accel_m_s2`` is not used: no ramps), plus one
        update step (the arrival is seen at the step after the profile ends)."""
        return self._profile_s(T_from, T_to, speed_m_s) + STEP_S

    def _travel(self, world: SimWorld, T_cmd_end: NDArray[np.float64], T_true_end: NDArray[np.float64],
                duration_s: float, protective_halfway: bool) -> None:
        """Move the tool along the line in real time; raise where a stop or a fault halts it."""
        T_cmd0, T_true0 = world.T_base_tool_commanded, world.raw_true_pose()
        cmd = _Line(T_cmd0, T_cmd_end)
        true = _Line(T_true0, T_true_end)
        t0 = time.monotonic()
        self._moving = True
        try:
            while True:
                s = min(1.0, (time.monotonic() - t0) / duration_s)
                if protective_halfway and s >= 0.5:
                    self._protective_stop = True
                if self._halt.is_set() or self._protective_stop or self._motion_aborted():
                    world.set_moving_pose(cmd.at(s), true.at(s))
                    world.keep()  # halted here: a restart finds the arm where it stopped
                    if self._dropped:
                        raise DeviceUnavailable(f"robot {self.robot_id}: the controller dropped off during the move")
                    if self._protective_stop:
                        raise DeviceOperationError(f"robot {self.robot_id}: protective stop during the move; "
                                                   "inspect the cell, then unlock the protective stop")
                    raise DeviceOperationError(f"robot {self.robot_id}: the move was stopped before it arrived")
                if s >= 1.0:
                    return
                world.set_moving_pose(cmd.at(s), true.at(s))
                self._halt.wait(min(STEP_S, duration_s))
        finally:
            self._moving = False

    def _stop(self) -> None:
        """Halt the tool where it is (an interrupted move raises), tracking too."""
        self._halt.set()
        if self._world is not None:
            self._world.tracker.stop()

    def tracks_conveyor(self) -> bool:
        return self._world is not None and self._world.belt is not None

    def _start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                        count: Callable[[], int] | None) -> int:
        world = self.world  # the virtual controller has the belt's encoder wired to it: ``count`` is not needed
        if world.belt is None:
            raise MotionRejected(f"robot {self.robot_id}: the scene has no conveyor to track")
        if self._moving:
            raise MotionRejected(f"robot {self.robot_id}: tracking starts with the arm standing still")
        world.settle_tracking()
        return world.tracker.start(direction_base, ticks_per_m, most_m)

    def _stop_tracking(self) -> None:
        if self._world is not None:
            self._world.tracker.stop()

    def _distance_to(self, target: NDArray[np.float64]) -> float:
        """From the commanded pose (the frame of the commands while tracking), m."""
        if self._world is None or self._dropped or not self._world.tracker.tracking:
            return super()._distance_to(target)
        return float(np.linalg.norm(target[:3, 3] - self._world.T_base_tool_commanded[:3, 3]))


class _Line:
    """Straight-line interpolation between two poses: position linear, orientation slerp."""

    def __init__(self, T0: NDArray[np.float64], T1: NDArray[np.float64]) -> None:
        self._p0, self._p1 = T0[:3, 3].copy(), T1[:3, 3].copy()
        self._slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))

    def at(self, s: float) -> NDArray[np.float64]:
        T = np.eye(4)
        T[:3, :3] = self._slerp([s]).as_matrix()[0]
        T[:3, 3] = self._p0 + s * (self._p1 - self._p0)
        return T
