"""Universal Robots arms over RTDE, through SDU Robotics' ``ur_rtde`` (``kind: ur_rtde``).

``ur_rtde`` holds the GIL while it blocks and may hang on a frozen peer, so this adapter never
calls it in the caller's process. Two child processes do (``ur_rtde_worker.py``), reached
through their links (``ur_rtde_link.py``):

- the **state worker** runs ``RTDEReceiveInterface`` and copies every new sample (TCP pose,
  joints, robot/safety mode, digital IO) into shared memory together with the host time it
  arrived; ``state()`` only reads that memory, so it never blocks, and it raises
  ``DeviceUnavailable`` when the newest sample is older than ``state_max_age_s``;
- the **control worker** runs ``DashboardClient`` and, on first use, ``RTDEControlInterface`` and
  ``RTDEIOInterface``; each request has a deadline, and a worker that misses it is killed.

A supervisor thread restarts a dead or silent state worker with exponential backoff
(``reconnect_initial_s`` doubling to ``reconnect_max_s``) and counts the outages (``health()``).
While the controller is unreachable the adapter fails fast: ``connect()`` returns as soon as the
worker is refused, and control requests are refused at once with ``DeviceUnavailable`` (a Stop is
still tried, within ``stop_timeout_s``). The workers die with the process that owns the adapter.
Moves are sent asynchronously (``moveL``/``moveJ`` with ``async=True``) and their completion is
observed in the state stream, so ``stop()`` can interrupt them.

**Conveyor tracking** is done from the host (``ur_rtde`` has no call for the controller's own): a servoL
stream in the control worker fed with cellctl's count (``ur_rtde_tracking.py``; docs/conveyor.md).

**When the service dies, the arm stops.** Before every move the control worker arms the
controller's RTDE watchdog (``setWatchdog(watchdog_min_frequency_hz)``) and then kicks it from its
own process; when the kicks stop for 1/f s (the service killed, its workers with it) the controller
stops the control script and the arm halts. A service that hangs but lives keeps kicking.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.geometry import rotation_angle, transform_to_ur_pose, ur_pose_to_transform
from drivers.base import (
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    DriverError,
    MotionLimits,
    MotionRejected,
    RobotState,
)
from drivers.health import DeviceHealth
from drivers.robot.ur_movel import movel_profile
from drivers.robot.ur_rtde_link import ControlLink, StateLink
from drivers.robot.ur_rtde_settings import ROBOT_MODES, SAFETY_MODES, URRTDESettings
from drivers.robot.ur_rtde_tracking import URHostTracking
from drivers.robot_base import DEFAULT_ACCEL_M_S2, turn_deg

log = logging.getLogger(__name__)

# -- the adapter ---------------------------------------------------------------------------------------

STOP_OPS = ("stopL", "stopJ")


class URRTDERobot(URHostTracking):
    """A Universal Robots arm through ``ur_rtde`` (receive, control, IO and dashboard interfaces)."""

    Settings = URRTDESettings

    def __init__(
        self, robot_id: str, settings: URRTDESettings | dict[str, Any], limits: MotionLimits
    ) -> None:
        super().__init__(robot_id, limits)
        self.config = (
            settings if isinstance(settings, URRTDESettings) else URRTDESettings.model_validate(settings)
        )
        ctx = mp.get_context("spawn")
        self._link = StateLink(robot_id, self.config, ctx, on_outage=self._controller_dropped)
        self._control = ControlLink(robot_id, self.config.host, self.config.frequency_hz,
                                    self.config.watchdog_min_frequency_hz, ctx, self._link.call_in_supervisor)
        self._stop_requested = threading.Event()
        self._ever_connected = False

    def tool_turn_speed_deg_s(self) -> float:
        """The most the controller turns the tool (``tool_turn_speed_deg_s``: the joints' speed limit), deg/s."""
        return self.config.tool_turn_speed_deg_s

    def linear_move_s(self, T_from: NDArray[np.float64], T_to: NDArray[np.float64], speed_m_s: float,
                      accel_m_s2: float = DEFAULT_ACCEL_M_S2) -> float:
        """``moveL``'s time as the controller profiles it (``drivers.robot.ur_movel``) at ``speed_m_s`` with the
        adapter's ``acceleration_m_s2`` (the one it sends; ``accel_m_s2`` is not used), plus two state samples
        (the arrival is seen in the stream)."""
        d = float(np.linalg.norm(np.asarray(T_to)[:3, 3] - np.asarray(T_from)[:3, 3]))
        angle = math.radians(turn_deg(T_from, T_to))
        duration, _ = movel_profile(d, angle, speed_m_s, self.config.acceleration_m_s2,
                                    math.radians(self.config.tool_turn_speed_deg_s))
        return duration + 2.0 / self.config.frequency_hz

    # -- connection ------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Start the state worker; wait for the first fresh sample or its refusal.

        The first connection waits up to ``connect_timeout_s``; a later one (the cell re-opening the
        robot after an outage) at most ``reconnect_wait_s``, so a caller never waits on a controller
        that is gone (unreachable hosts included) longer than the service's own deadline.
        """
        self._link.start()
        wait_s = self.config.connect_timeout_s
        if self._ever_connected:
            wait_s = min(wait_s, self.config.reconnect_wait_s)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if self._link.fresh_age() is not None:
                self._ever_connected = True
                # the control worker boots in the background, so the first move's deadline does not pay for it
                self._control.prestart()
                return
            failure = self._link.failure
            if failure:  # refused or lost: the peer is down now, do not make the caller wait
                raise DeviceUnavailable(
                    f"robot {self.robot_id}: {failure}; check that the controller at {self.config.host} is on "
                    "and that port 30004 is open. The adapter keeps retrying in the background.")
            time.sleep(0.01)
        raise DeviceUnavailable(
            f"robot {self.robot_id}: no RTDE state from {self.config.host} within "
            f"{wait_s:g} s ({self._link.reason}); check that the controller is on, reachable "
            "and that port 30004 is open. The adapter keeps retrying in the background."
        )

    def close(self) -> None:
        """Stop the workers and the supervisor; safe to call twice."""
        if self._link.running:
            # the control worker disconnects cleanly first (it was started by the supervisor thread)
            self._control.close(graceful=True)
        self._link.stop()
        self._control.close()

    def health(self) -> DeviceHealth:
        """Availability, outage and reconnect counts, the last outage's duration, the newest sample's age."""
        age = self._link.buffer.age_s()
        available = age is not None and age <= self.config.state_max_age_s and not self._link.failure
        if not available:
            self._link.note_staleness()
        return self._link.outages.health(available, reason=self._unavailable_reason(age),
                                         last_outage_s=self._link.outages.last_outage_s, state_age_s=age)

    def _unavailable_reason(self, age: float | None) -> str:
        if not self._link.running:
            return "not connected (call connect())"
        why = self._link.reason or self._link.failure or "waiting for data"
        if age is None:
            return f"no RTDE state received yet from {self.config.host}: {why}"
        return (
            f"newest RTDE state is {age:.2f} s old (limit {self.config.state_max_age_s} s): {why}; "
            "reconnecting by itself"
        )

    # -- state ------------------------------------------------------------------------------------------
    def state(self) -> RobotState:
        """The newest sample; ``DeviceUnavailable`` when it is older than ``state_max_age_s`` or the state
        worker has lost the controller (its last samples are no news)."""
        if not self._link.running:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected (call connect())")
        s = self._link.buffer.snapshot()
        age = None if s is None else time.time() - s.host_time_s
        if s is None or age is None or age > self.config.state_max_age_s or self._link.failure:
            self._link.note_staleness()
            raise DeviceUnavailable(f"robot {self.robot_id}: {self._unavailable_reason(age)}")
        pose = np.array(s.pose)
        qd = np.array(s.qd)
        tcp_speed = np.array(s.tcp_speed)
        moving = bool(np.max(np.abs(qd)) > 1e-4 or np.linalg.norm(tcp_speed[:3]) > 1e-5)
        robot_mode = ROBOT_MODES.get(s.robot_mode, f"mode_{s.robot_mode}")
        safety_mode = SAFETY_MODES.get(s.safety_mode, f"safety_{s.safety_mode}")
        return RobotState(
            T_base_tool=ur_pose_to_transform(pose),
            joints_rad=np.array(s.q),
            timestamp_s=s.host_time_s,
            moving=moving,
            mode=robot_mode if safety_mode == "normal" else safety_mode,
            metadata={
                "robot_mode": robot_mode,
                "safety_mode": safety_mode,
                "program_running": s.runtime_state == 2,
                "controller_time_s": s.controller_time_s,
                "digital_in": [bool(s.digital_in >> i & 1) for i in range(8)],
                "digital_out": [bool(s.digital_out >> i & 1) for i in range(8)],
                "ur_pose": pose.tolist(),
                "tcp_speed_m_s": float(np.linalg.norm(tcp_speed[:3])),
            },
        )

    # -- control worker ------------------------------------------------------------------------------
    def _request(self, op: str, args: tuple[Any, ...], timeout_s: float) -> Any:
        """One control/dashboard call; refused at once while the controller is unreachable (no waits)."""
        if not self._link.running:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected (call connect())")
        if op not in STOP_OPS and self._link.fresh_age() is None:
            raise DeviceUnavailable(
                f"robot {self.robot_id}: {op} refused: {self._unavailable_reason(self._link.buffer.age_s())}")
        return self._control.request(op, args, timeout_s)

    # -- motion ------------------------------------------------------------------------------------------
    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """The controller's own forward kinematics (so joint moves are checked against the envelope)."""
        try:
            pose = self._request("fk", (list(map(float, joints_rad)), []), self.config.command_timeout_s)
        except (DeviceUnavailable, DeviceTimeout, DeviceOperationError) as exc:
            raise MotionRejected(
                f"robot {self.robot_id}: cannot check the joint target against the envelope: {exc}"
            ) from exc
        return ur_pose_to_transform(np.asarray(pose, dtype=np.float64))

    def _require_ready(self) -> RobotState:
        st = self._state_while_moving()
        while st is None:  # a late sample; a lost link raises within stall_timeout_s
            time.sleep(0.005)
            st = self._state_while_moving()
        if st.metadata["safety_mode"] != "normal":
            raise DeviceOperationError(
                f"robot {self.robot_id} is in {st.metadata['safety_mode']}; clear it on the pendant or with "
                "unlock_protective_stop() before moving"
            )
        if st.metadata["robot_mode"] != "running":
            raise DeviceOperationError(
                f"robot {self.robot_id} is {st.metadata['robot_mode']}, not running; power it on and release "
                "the brakes (power_on(), brake_release()) before moving"
            )
        return st

    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        if self._tracking is not None:
            self._tracked_move(self._tracking, T_base_tool, speed_m_s)
            return
        st = self._require_ready()
        pose = [float(v) for v in transform_to_ur_pose(T_base_tool)]
        expected = self.linear_move_s(st.T_base_tool, T_base_tool, speed_m_s) + 1.0
        self._stop_requested.clear()
        ok = self._request(
            "moveL", (pose, speed_m_s, self.config.acceleration_m_s2, True), self.config.command_timeout_s
        )
        if not ok:
            raise DeviceOperationError(self._refusal("moveL"))
        self._wait_arrival(
            lambda s: self._pose_reached(s, T_base_tool), expected + self.config.command_timeout_s
        )

    def _move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None:
        st = self._require_ready()
        q = [float(v) for v in joints_rad]
        expected = float(np.max(np.abs(np.asarray(q) - st.joints_rad))) / speed_rad_s + 1.0
        self._stop_requested.clear()
        ok = self._request(
            "moveJ",
            (q, speed_rad_s, self.config.joint_acceleration_rad_s2, True),
            self.config.command_timeout_s,
        )
        if not ok:
            raise DeviceOperationError(self._refusal("moveJ"))
        self._wait_arrival(
            lambda s: float(np.max(np.abs(s.joints_rad - np.asarray(q)))) <= self.config.joint_tolerance_rad,
            expected + self.config.command_timeout_s,
        )

    def _pose_reached(self, s: RobotState, T: NDArray[np.float64]) -> bool:
        d_mm = 1000.0 * float(np.linalg.norm(s.T_base_tool[:3, 3] - T[:3, 3]))
        angle = rotation_angle(s.T_base_tool[:3, :3].T @ T[:3, :3])
        return d_mm <= self.config.position_tolerance_mm and angle <= math.radians(0.05)

    def _refusal(self, op: str) -> str:
        try:
            st = self.state()
            why = (
                f"robot mode {st.metadata['robot_mode']}, safety {st.metadata['safety_mode']}, "
                f"control script {'running' if st.metadata['program_running'] else 'not running'}"
            )
        except DeviceUnavailable as exc:
            why = str(exc)
        return f"robot {self.robot_id}: the controller refused {op} ({why}); check the pendant for errors"

    def _state_while_moving(self) -> RobotState | None:
        """The newest state; None in a short gap of the stream (a late sample, the worker streaming): a
        move is not abandoned for it. A lost link (worker failed, or silent ``stall_timeout_s``) raises."""
        try:
            return self.state()
        except DeviceUnavailable:
            age = self._link.buffer.age_s()
            if self._link.failure or age is None or age > self.config.stall_timeout_s:
                raise
            return None

    def _wait_arrival(self, arrived: Callable[[RobotState], bool], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            s = self._state_while_moving()  # first: a lost controller answers as lost, not as a failed stop
            if self._motion_aborted() and not self._stop_requested.is_set():
                try:
                    self._stop()  # a Stop raced the command, or a dropout latched the robot
                except DriverError:
                    self._state_while_moving()  # the controller is gone: say so (DeviceUnavailable)
                    raise
            if self._stop_requested.is_set():
                raise DeviceOperationError(f"robot {self.robot_id}: the move was stopped before it arrived")
            if s is None:
                pass  # a late sample: the deadline below still holds
            elif s.metadata["safety_mode"] != "normal":
                raise DeviceOperationError(
                    f"robot {self.robot_id}: {s.metadata['safety_mode']} during the move; "
                    "inspect the cell, then unlock_protective_stop()"
                )
            elif not s.metadata["program_running"]:
                raise DeviceOperationError(
                    f"robot {self.robot_id}: the control script stopped during the move "
                    "(target unreachable, stopped on the pendant, or its RTDE watchdog expired)"
                )
            elif arrived(s) and not s.moving:
                return
            if time.monotonic() > deadline:
                try:
                    self._stop()
                except DriverError as exc:
                    log.error("robot %s: stopping a late move failed: %s", self.robot_id, exc)
                    raise DeviceTimeout(
                        f"robot {self.robot_id}: the move did not arrive within {timeout_s:.1f} s and STOPPING "
                        f"IT FAILED ({exc}); check the robot now"
                    ) from exc
                raise DeviceTimeout(
                    f"robot {self.robot_id}: the move did not arrive within {timeout_s:.1f} s; "
                    "the robot was told to stop"
                )
            time.sleep(0.002)

    def _stop(self) -> None:
        """Decelerate any motion this adapter commanded (stopL, then stopJ), within ``stop_timeout_s`` each;
        a tracking stream ends first (no pose is streamed after the stop)."""
        self._stop_requested.set()
        self._end_tracking()
        if not self._control.started:
            return  # no move was ever sent through this adapter
        timeout_s = min(self.config.stop_timeout_s, self.config.command_timeout_s)
        # stopL first; if the controller cannot be told that, stopJ would not get through either
        self._request("stopL", (self.config.acceleration_m_s2 * 5, False), timeout_s)
        self._request("stopJ", (self.config.joint_acceleration_rad_s2 * 5, False), timeout_s)

    # -- IO and dashboard ----------------------------------------------------------------------------
    def set_digital_out(self, channel: int, value: bool) -> None:
        """Set standard digital output ``channel`` (0-7) through the RTDE IO interface."""
        if not 0 <= channel <= 7:
            raise DeviceOperationError(
                f"robot {self.robot_id}: standard digital output {channel} is not in 0..7"
            )
        if not self._request("digital_out", (channel, bool(value)), self.config.command_timeout_s):
            raise DeviceOperationError(f"robot {self.robot_id}: setting digital output {channel} failed")

    def dashboard(self, command: str) -> Any:
        """Run one ``DashboardClient`` method (``robotmode``, ``safetystatus``, ``powerOn``, ...)."""
        allowed = {
            "robotmode",
            "safetystatus",
            "safetymode",
            "programState",
            "polyscopeVersion",
            "powerOn",
            "powerOff",
            "brakeRelease",
            "unlockProtectiveStop",
            "closeSafetyPopup",
            "running",
        }
        if command not in allowed:
            raise DeviceOperationError(
                f"robot {self.robot_id}: dashboard command {command!r} is not one of "
                f"{', '.join(sorted(allowed))}"
            )
        return self._request("dashboard", (command,), self.config.command_timeout_s)

    def power_on(self) -> None:
        self.dashboard("powerOn")

    def brake_release(self) -> None:
        self.dashboard("brakeRelease")

    def unlock_protective_stop(self) -> None:
        self.dashboard("unlockProtectiveStop")
