"""The UR adapter's conveyor tracking from the host (``URRTDERobot``'s base; docs/conveyor.md).

``start_tracking`` starts a servo stream in the adapter's control worker (``ur_track_stream``) fed from this
process (``ur_tracking.HostTracking``); moves while it tracks are lines in the belt's frame; a Stop ends the
stream before the adapter's ``stopL``. Units: poses ``T_base_tool`` 4x4 in metres.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.geometry import ur_pose_to_transform
from drivers.base import DeviceOperationError, DeviceTimeout, DriverError, MotionLimits, MotionRejected, RobotBase
from drivers.robot.ur_rtde_link import ControlLink, StateLink
from drivers.robot.ur_rtde_settings import URRTDESettings
from drivers.robot.ur_tracking import HostTracking
from drivers.values import RobotState

log = logging.getLogger(__name__)

FIRST_SPEED_S = 0.1
"""Before the adapter's first tracking, the belt's speed is taken from the count over this long (s); later
trackings start from the speed the last one ended with."""


class URHostTracking(RobotBase):
    """``RobotBase`` with host-side conveyor tracking over the UR adapter's control link."""

    config: URRTDESettings
    _link: StateLink
    _control: ControlLink
    _stop_requested: threading.Event

    def __init__(self, robot_id: str, limits: MotionLimits) -> None:
        super().__init__(robot_id, limits)
        self._tracking: HostTracking | None = None
        self._tracking_lag_m = 0.0
        self._tracking_speed = 0.0
        """What the last tracking learnt: the stream's latency (m along the belt) and the belt's speed (ticks/s)."""
        self._tracking_report: dict[str, float | int] | None = None
        """The last tracking's measured error (``HostTracking.report``), kept after it ended."""

    def tracking_report(self) -> dict[str, float | int] | None:
        """The last tracking's measured error (``HostTracking.report``: ``rms_mm``, ``max_mm``, ``samples``,
        ``servo_steps``), kept after it ended; None before the first."""
        return self._tracking_report

    # -- the adapter's own (``URRTDERobot``) -----------------------------------------------------------
    def _request(self, op: str, args: tuple[Any, ...], timeout_s: float) -> Any:
        raise NotImplementedError

    def _require_ready(self) -> RobotState:
        raise NotImplementedError

    def _state_while_moving(self) -> RobotState | None:
        raise NotImplementedError

    # -- tracking ------------------------------------------------------------------------------------------
    def tracks_conveyor(self) -> bool:
        return True

    def _start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                        count: Callable[[], int] | None) -> int:
        if count is None:
            raise MotionRejected(f"robot {self.robot_id}: tracking from the host needs the belt's count (a belt "
                                 "run passes its conveyor's); the controller's own tracking is not used "
                                 "(docs/conveyor.md)")
        st = self._require_ready()
        if st.moving:
            raise MotionRejected(f"robot {self.robot_id}: tracking starts with the arm standing still")
        self._stop_requested.clear()
        if self._tracking_speed == 0.0:  # the first tracking: the belt's speed from the count before it starts
            t0, c0 = time.monotonic(), count()
            time.sleep(FIRST_SPEED_S)
            self._tracking_speed = (count() - c0) / (time.monotonic() - t0)
        tracking = HostTracking(
            self.robot_id, self._control.track, count=count, direction_base=direction_base, ticks_per_m=ticks_per_m,
            most_m=most_m, T_belt_start=st.T_base_tool, rotvec=[float(v) for v in st.metadata["ur_pose"][3:6]],
            limits=self.limits, actual=self._actual_sample, lag_m=self._tracking_lag_m,
            speed_ticks_s=self._tracking_speed)
        self._tracking = tracking
        tracking.begin()
        try:
            self._request("track_begin", (), self.config.command_timeout_s)
        except DriverError:
            self._end_tracking()
            raise
        return tracking.ticks0

    def _stop_tracking(self) -> None:
        if self._end_tracking():
            try:
                self._request("servoStop", (self.config.acceleration_m_s2 * 5,), self.config.stop_timeout_s)
            except DriverError as exc:
                log.warning("robot %s: ending the servo stream failed: %s", self.robot_id, exc)

    def _end_tracking(self) -> bool:
        """End the stream (the worker sends no pose after this returns); True when one ran."""
        tracking, self._tracking = self._tracking, None
        if tracking is None:
            return False
        tracking.end()
        self._tracking_lag_m, self._tracking_speed = tracking.lag_m, tracking.speed_ticks_s()
        self._tracking_report = tracking.report()
        return True

    def _actual_sample(self) -> tuple[NDArray[np.float64], float] | None:
        s = self._link.buffer.snapshot()
        if s is None:
            return None
        return ur_pose_to_transform(np.array(s.pose)), time.monotonic() - (time.time() - s.host_time_s)

    def _tracked_move(self, tracking: HostTracking, T_belt: NDArray[np.float64], speed_m_s: float) -> None:
        """A linear move in the belt's frame while tracking: streamed, arrived when the arm is on the moving target."""
        self._require_ready()
        t_end = time.monotonic() + tracking.move(T_belt, speed_m_s)
        deadline = t_end + self.config.command_timeout_s
        while True:
            if self._stop_requested.is_set() or self._motion_aborted():
                raise DeviceOperationError(f"robot {self.robot_id}: the move was stopped before it arrived")
            if tracking.error is not None:
                raise DeviceOperationError(f"robot {self.robot_id}: {tracking.error}")
            s = self._state_while_moving()
            if s is not None and s.metadata["safety_mode"] != "normal":
                raise DeviceOperationError(f"robot {self.robot_id}: {s.metadata['safety_mode']} while tracking")
            if s is not None and time.monotonic() >= t_end:
                sample = self._actual_sample()
                if sample is not None and tracking.arrived_within_mm(*sample) <= self.config.tracking_tolerance_mm:
                    return
            if time.monotonic() > deadline:
                self._stop()
                raise DeviceTimeout(f"robot {self.robot_id}: the tracked move did not arrive within "
                                    f"{self.config.command_timeout_s:g} s of its end; the robot was told to stop")
            time.sleep(0.002)

    def _distance_to(self, target: NDArray[np.float64]) -> float:
        """While tracking: from the tool's pose in the belt's frame (the frame of the commands), m."""
        tracking = self._tracking
        if tracking is None:
            return super()._distance_to(target)
        return float(np.linalg.norm(target[:3, 3] - tracking.belt_position(time.monotonic())))
