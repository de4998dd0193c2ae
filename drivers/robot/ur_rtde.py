"""Universal Robots arms over RTDE, through SDU Robotics' ``ur_rtde`` (``kind: ur_rtde``).

``ur_rtde`` holds the GIL while it blocks and may hang on a frozen peer, so this adapter never
calls it in the caller's process. Two child processes do:

- the **state worker** runs ``RTDEReceiveInterface`` and copies every new sample (TCP pose,
  joints, robot/safety mode, digital IO) into shared memory together with the host time it
  arrived; ``state()`` only reads that memory, so it never blocks, and it raises
  ``DeviceUnavailable`` when the newest sample is older than ``state_max_age_s``;
- the **control worker** runs ``DashboardClient`` and, on first use, ``RTDEControlInterface`` and
  ``RTDEIOInterface``; each request has a deadline, and a worker that misses it is killed.

A supervisor thread restarts a dead or silent state worker with exponential backoff
(``reconnect_initial_s`` doubling to ``reconnect_max_s``) and counts the outages (``health()``).
Moves are sent asynchronously (``moveL``/``moveJ`` with ``async=True``) and their completion is
observed in the state stream, so ``stop()`` can interrupt them.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import multiprocessing as mp
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from calibration.geometry import rotation_angle, transform_to_ur_pose, ur_pose_to_transform
from drivers.base import (
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    DriverError,
    MotionLimits,
    MotionRejected,
    RobotBase,
    RobotState,
)
from drivers.robot._ur_rtde_worker import (
    _DIN,
    _DOUT,
    _HOST_T,
    _POSE,
    _Q,
    _QD,
    _ROBOT_MODE,
    _ROBOT_T,
    _RUNTIME,
    _SAFETY_MODE,
    _SEQ,
    _SHM_SIZE,
    _TCP_SPEED,
    _control_worker,
    _state_worker,
)

log = logging.getLogger(__name__)

ROBOT_MODES = {
    -1: "no_controller",
    0: "disconnected",
    1: "confirm_safety",
    2: "booting",
    3: "power_off",
    4: "power_on",
    5: "idle",
    6: "backdrive",
    7: "running",
    8: "updating_firmware",
}
SAFETY_MODES = {
    1: "normal",
    2: "reduced",
    3: "protective_stop",
    4: "recovery",
    5: "safeguard_stop",
    6: "system_emergency_stop",
    7: "robot_emergency_stop",
    8: "violation",
    9: "fault",
    10: "validate_joint_id",
    11: "undefined_safety_mode",
}


class URRTDESettings(BaseModel):
    """Settings of a Universal Robots arm reached over RTDE."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field(min_length=1, description="controller IP address or host name")
    frequency_hz: float = Field(500.0, gt=0, le=500, description="RTDE rate: 500 e-Series, 125 CB3")
    state_max_age_s: float = Field(0.1, gt=0, le=10, description="older samples are never served as current")
    connect_timeout_s: float = Field(5.0, gt=0, le=120)
    stall_timeout_s: float = Field(
        1.0, gt=0, le=60, description="no new sample for this long: the connection is restarted"
    )
    command_timeout_s: float = Field(
        10.0, gt=0, le=600, description="deadline of a control request, added to a move's duration"
    )
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)
    acceleration_m_s2: float = Field(1.2, gt=0, le=10)
    joint_acceleration_rad_s2: float = Field(1.4, gt=0, le=40)
    position_tolerance_mm: float = Field(0.2, gt=0, le=10, description="a move has arrived within this")
    joint_tolerance_rad: float = Field(0.002, gt=0, le=0.1)


# -- the adapter ---------------------------------------------------------------------------------------


class URRTDERobot(RobotBase):
    """A Universal Robots arm through ``ur_rtde`` (receive, control, IO and dashboard interfaces)."""

    Settings = URRTDESettings

    def __init__(
        self, robot_id: str, settings: URRTDESettings | dict[str, Any], limits: MotionLimits
    ) -> None:
        super().__init__(robot_id, limits)
        self.config = (
            settings if isinstance(settings, URRTDESettings) else URRTDESettings.model_validate(settings)
        )
        self._ctx = mp.get_context("spawn")
        self._shm: Any = self._ctx.Array(ctypes.c_double, _SHM_SIZE)
        self._error = self._ctx.Array(ctypes.c_char, 256)
        self._stop_worker = self._ctx.Event()
        self._state_proc: Any = None
        self._supervisor: threading.Thread | None = None
        self._closing = threading.Event()
        self._lock = threading.RLock()
        self._control_lock = threading.Lock()
        self._control_proc: Any = None
        self._control_conn: Connection | None = None
        self._stop_requested = threading.Event()
        self._next_attempt_s = 0.0
        self._backoff_s = self.config.reconnect_initial_s
        self._reason = "not connected"
        self.outages = 0
        self.reconnects = 0
        self.last_outage_s = 0.0
        self._outage_since: float | None = None
        self._outage_lock = threading.Lock()
        self._last_seq = 0.0
        self._last_seq_change = 0.0
        self._worker_streaming = False

    # -- connection and supervision -----------------------------------------------------------------
    def connect(self) -> None:
        """Start the state worker and wait for the first fresh sample (``connect_timeout_s``)."""
        with self._lock:
            if self._supervisor is None:
                self._closing.clear()
                self._start_state_worker()
                self._supervisor = threading.Thread(
                    target=self._supervise, name=f"ur-{self.robot_id}", daemon=True
                )
                self._supervisor.start()
        deadline = time.monotonic() + self.config.connect_timeout_s
        while time.monotonic() < deadline:
            if self._fresh_age() is not None:
                return
            time.sleep(0.01)
        raise DeviceUnavailable(
            f"robot {self.robot_id}: no RTDE state from {self.config.host} within "
            f"{self.config.connect_timeout_s} s ({self._reason}); check that the controller is on, reachable "
            "and that port 30004 is open. The adapter keeps retrying in the background."
        )

    def _start_state_worker(self) -> None:
        self._error.value = b""
        self._stop_worker.clear()
        proc = self._ctx.Process(
            target=_state_worker,
            name=f"ur-state-{self.robot_id}",
            daemon=True,
            args=(self.config.host, self.config.frequency_hz, self._shm, self._error, self._stop_worker),
        )
        proc.start()
        self._state_proc = proc
        self._worker_streaming = False
        self._last_seq_change = time.monotonic()

    def _kill_state_worker(self) -> None:
        proc = self._state_proc
        self._state_proc = None
        if proc is None:
            return
        self._stop_worker.set()
        proc.join(timeout=0.3)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=2.0)

    def _supervise(self) -> None:
        while not self._closing.wait(0.02):
            with self._lock:
                now = time.monotonic()
                seq = self._shm[_SEQ]
                self._note_staleness()
                if seq != self._last_seq:
                    self._last_seq = seq
                    self._last_seq_change = now
                    self._worker_streaming = True
                    self._backoff_s = self.config.reconnect_initial_s
                    with self._outage_lock:
                        if self._outage_since is not None:
                            self.last_outage_s = now - self._outage_since
                            self._outage_since = None
                    self._reason = ""
                    continue
                proc = self._state_proc
                if proc is not None and proc.is_alive():
                    silent_s = now - self._last_seq_change
                    # a new worker gets the connect timeout to produce its first sample
                    allowed_s = (
                        self.config.stall_timeout_s
                        if self._worker_streaming
                        else self.config.connect_timeout_s
                    )
                    if silent_s < allowed_s:
                        continue
                    self._reason = (
                        f"no RTDE data from {self.config.host} for {silent_s:.1f} s "
                        "(controller frozen or network down)"
                    )
                    self._kill_state_worker()
                elif proc is not None:
                    message = self._error.value.decode(errors="replace")
                    self._reason = message or f"RTDE worker for {self.config.host} exited"
                    self._kill_state_worker()
                if self._state_proc is None:
                    if self._next_attempt_s == 0.0:
                        self._next_attempt_s = now + self._backoff_s
                    if now >= self._next_attempt_s:
                        self._next_attempt_s = 0.0
                        self._backoff_s = min(self._backoff_s * 2.0, self.config.reconnect_max_s)
                        self.reconnects += 1
                        self._start_state_worker()

    def close(self) -> None:
        """Stop the workers and the supervisor; safe to call twice."""
        self._closing.set()
        sup = self._supervisor
        if sup is not None and sup is not threading.current_thread():
            sup.join(timeout=2.0)
        self._supervisor = None
        with self._lock:
            self._kill_state_worker()
        self._kill_control_worker(graceful=True)

    def _note_staleness(self) -> None:
        """Open an outage (counted once) when the newest sample is too old; the supervisor closes it."""
        age = self._sample_age()
        if age is not None and age > self.config.state_max_age_s:
            with self._outage_lock:
                if self._outage_since is None:
                    self._outage_since = time.monotonic() - (age - self.config.state_max_age_s)
                    self.outages += 1

    def health(self) -> dict[str, Any]:
        """``available``, ``reason``, outage and reconnect counts, the newest sample's age."""
        age = self._sample_age()
        available = age is not None and age <= self.config.state_max_age_s
        if not available:
            self._note_staleness()
        return {
            "available": available,
            "reason": "" if available else self._unavailable_reason(age),
            "outages": self.outages,
            "reconnects": self.reconnects,
            "last_outage_s": self.last_outage_s,
            "state_age_s": age,
        }

    # -- state ------------------------------------------------------------------------------------------
    def _snapshot(self) -> list[float]:
        with self._shm.get_lock():
            return list(self._shm[:])

    def _sample_age(self) -> float | None:
        host_t = self._shm[_HOST_T]
        return None if host_t == 0.0 else time.time() - host_t

    def _fresh_age(self) -> float | None:
        age = self._sample_age()
        return age if age is not None and age <= self.config.state_max_age_s else None

    def _unavailable_reason(self, age: float | None) -> str:
        if self._supervisor is None:
            return "not connected (call connect())"
        why = self._reason or "waiting for data"
        if age is None:
            return f"no RTDE state received yet from {self.config.host}: {why}"
        return (
            f"newest RTDE state is {age:.2f} s old (limit {self.config.state_max_age_s} s): {why}; "
            "reconnecting by itself"
        )

    def state(self) -> RobotState:
        """The newest sample; ``DeviceUnavailable`` when it is older than ``state_max_age_s``."""
        s = self._snapshot()
        age = None if s[_HOST_T] == 0.0 else time.time() - s[_HOST_T]
        if self._supervisor is None:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected (call connect())")
        if age is None or age > self.config.state_max_age_s:
            self._note_staleness()
            raise DeviceUnavailable(f"robot {self.robot_id}: {self._unavailable_reason(age)}")
        pose = np.array(s[_POSE : _POSE + 6])
        qd = np.array(s[_QD : _QD + 6])
        tcp_speed = np.array(s[_TCP_SPEED : _TCP_SPEED + 6])
        moving = bool(np.max(np.abs(qd)) > 1e-4 or np.linalg.norm(tcp_speed[:3]) > 1e-5)
        robot_mode = ROBOT_MODES.get(int(s[_ROBOT_MODE]), f"mode_{int(s[_ROBOT_MODE])}")
        safety_mode = SAFETY_MODES.get(int(s[_SAFETY_MODE]), f"safety_{int(s[_SAFETY_MODE])}")
        din, dout = int(s[_DIN]), int(s[_DOUT])
        return RobotState(
            T_base_tool=ur_pose_to_transform(pose),
            joints_rad=np.array(s[_Q : _Q + 6]),
            timestamp_s=s[_HOST_T],
            moving=moving,
            mode=robot_mode if safety_mode == "normal" else safety_mode,
            metadata={
                "robot_mode": robot_mode,
                "safety_mode": safety_mode,
                "program_running": int(s[_RUNTIME]) == 2,
                "controller_time_s": s[_ROBOT_T],
                "digital_in": [bool(din >> i & 1) for i in range(8)],
                "digital_out": [bool(dout >> i & 1) for i in range(8)],
                "ur_pose": pose.tolist(),
                "tcp_speed_m_s": float(np.linalg.norm(tcp_speed[:3])),
            },
        )

    # -- control worker ------------------------------------------------------------------------------
    def _kill_control_worker(self, graceful: bool = False) -> None:
        proc, conn = self._control_proc, self._control_conn
        self._control_proc = None
        self._control_conn = None
        if conn is not None:
            if graceful and proc is not None and proc.is_alive():
                with contextlib.suppress(OSError, ValueError):
                    conn.send(("close", ()))
                    if conn.poll(1.5):
                        conn.recv()
            with contextlib.suppress(OSError):
                conn.close()
        if proc is not None:
            proc.join(timeout=0.5 if graceful else 0.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)

    def _request(self, op: str, args: tuple[Any, ...], timeout_s: float) -> Any:
        """Run one ur_rtde control/dashboard call in the control worker with a deadline."""
        with self._control_lock:
            if self._control_proc is None or not self._control_proc.is_alive():
                self._kill_control_worker()
                parent, child = self._ctx.Pipe()
                proc = self._ctx.Process(
                    target=_control_worker,
                    name=f"ur-control-{self.robot_id}",
                    args=(self.config.host, self.config.frequency_hz, child),
                    daemon=True,
                )
                proc.start()
                child.close()
                self._control_proc, self._control_conn = proc, parent
            conn = self._control_conn
            assert conn is not None
            try:
                conn.send((op, args))
                ready = conn.poll(timeout_s)
                reply = conn.recv() if ready else None
            except (OSError, EOFError) as exc:
                self._kill_control_worker()
                raise DeviceUnavailable(
                    f"robot {self.robot_id}: control connection to {self.config.host} "
                    f"died during {op}; it is restarted on the next command"
                ) from exc
            if reply is None:
                self._kill_control_worker()
                raise DeviceTimeout(
                    f"robot {self.robot_id}: {op} got no answer from {self.config.host} within "
                    f"{timeout_s:.1f} s; the control connection was reset, check the controller"
                )
        status, value = reply
        if status == "error":
            raise DeviceOperationError(f"robot {self.robot_id}: {op} failed on {self.config.host}: {value}")
        return value

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
        st = self.state()
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
        st = self._require_ready()
        pose = [float(v) for v in transform_to_ur_pose(T_base_tool)]
        dist = float(np.linalg.norm(T_base_tool[:3, 3] - st.T_base_tool[:3, 3]))
        expected = dist / speed_m_s + speed_m_s / self.config.acceleration_m_s2 + 1.0
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

    def _wait_arrival(self, arrived: Any, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            s = self.state()
            if self._motion_aborted() and not self._stop_requested.is_set():
                self._stop()  # a Stop raced the command (it came before the move was sent)
            if self._stop_requested.is_set():
                raise DeviceOperationError(f"robot {self.robot_id}: the move was stopped before it arrived")
            if s.metadata["safety_mode"] != "normal":
                raise DeviceOperationError(
                    f"robot {self.robot_id}: {s.metadata['safety_mode']} during the move; "
                    "inspect the cell, then unlock_protective_stop()"
                )
            if not s.metadata["program_running"]:
                raise DeviceOperationError(
                    f"robot {self.robot_id}: the control script stopped during the move "
                    "(target unreachable or stopped on the pendant)"
                )
            if arrived(s) and not s.moving:
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
        """Decelerate any motion this adapter commanded (stopL, then stopJ)."""
        self._stop_requested.set()
        if self._control_proc is None:
            return
        self._request("stopL", (self.config.acceleration_m_s2 * 5, False), self.config.command_timeout_s)
        self._request(
            "stopJ", (self.config.joint_acceleration_rad_s2 * 5, False), self.config.command_timeout_s
        )

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
