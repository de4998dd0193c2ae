"""The driver contract: device Protocols, the values that cross them, and typed errors.

Code that *uses* devices depends on the Protocols ``Camera``, ``Robot`` and ``DigitalIO``.
Code that *implements* a robot subclasses ``RobotBase``: its public ``move_linear`` /
``move_joint`` run the one envelope and speed check (``MotionLimits``) and only then call the
adapter's ``_move_linear`` / ``_move_joint`` hooks, so no adapter can bypass the check.

Units: poses are ``T_base_tool`` 4x4 in metres; joints in radians; speeds in m/s (linear) and
rad/s (joint); envelopes in millimetres, as the config states them (``*_mm``).
"""

from __future__ import annotations

import abc
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import NDArray

# -- errors (drivers/errors.py) and motion ownership (drivers/motion.py) -------------------------
from drivers.errors import (  # re-exported: the errors are part of the contract
    DeviceInitError,
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    DriverError,
    MotionRejected,
)
from drivers.health import DeviceHealth
from drivers.motion import MotionOwner, MotionSession, RobotBusy, RobotStopped, move_deadline_s

__all__ = [
    "Camera", "CameraBase", "DeviceBase", "DeviceInitError", "DeviceOperationError", "DeviceTimeout",
    "DeviceUnavailable", "DigitalIO", "DigitalIOBase", "DriverError", "Frame", "MotionLimits", "MotionOwner",
    "MotionRejected", "MotionSession", "Robot", "RobotBase", "RobotBusy", "RobotState", "RobotStopped",
]

log = logging.getLogger(__name__)


# -- values -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    """One camera image: pixels (H, W) grey or (H, W, 3) BGR, and when it was taken."""

    pixels: NDArray[Any]
    timestamp_s: float
    """Capture time, seconds since the Unix epoch (camera clock mapped to host when available)."""
    frame_id: int = 0
    camera_id: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def meta(self) -> dict[str, Any]:
        """``metadata`` (the name docs/conveyor.md uses: ``Frame.meta["encoder_ticks"]``, a belt's count
        latched at the exposure)."""
        return self.metadata

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (int(self.pixels.shape[1]), int(self.pixels.shape[0]))


@dataclass(frozen=True)
class RobotState:
    """The robot's state: ``T_base_tool`` (4x4, metres), joints (radians), time, modes."""

    T_base_tool: NDArray[np.float64]
    joints_rad: NDArray[np.float64]
    timestamp_s: float
    """When the state was sampled, seconds since the Unix epoch (host clock)."""
    moving: bool = False
    mode: str = "running"
    metadata: dict[str, Any] = field(default_factory=dict)

    def age_s(self, now_s: float | None = None) -> float:
        return (time.time() if now_s is None else now_s) - self.timestamp_s


# -- motion limits ------------------------------------------------------------------------------


@dataclass(frozen=True)
class MotionLimits:
    """The workspace envelope (a box in the base frame, mm) and the speed limits."""

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    max_linear_speed_m_s: float
    max_joint_speed_rad_s: float = math.pi / 2
    joint_limits_rad: tuple[tuple[float, float], ...] | None = None
    tool_down_cone_deg: float | None = 60.0
    """Largest angle between the tool's z axis and the base's -z ("down"); None: not checked."""
    max_move_duration_s: float = 60.0
    """A move that would take longer at the commanded speed is refused (too slow to supervise)."""
    move_deadline_slack_s: float = 5.0
    """A move may take 1.5x its nominal duration plus this (s) before it is stopped as late."""

    def check_pose(self, T_base_tool: NDArray[np.float64]) -> None:
        """Raise MotionRejected when the tool position is outside the envelope."""
        T = np.asarray(T_base_tool, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise MotionRejected("target pose must be a finite 4x4 T_base_tool matrix")
        p_mm = T[:3, 3] * 1000.0
        for axis, value, (lo, hi) in zip("xyz", p_mm, (self.x_mm, self.y_mm, self.z_mm), strict=True):
            if not lo <= value <= hi:
                raise MotionRejected(
                    f"target {axis} = {value:.1f} mm is outside the workspace envelope "
                    f"[{lo:.1f}, {hi:.1f}] mm; choose a pose inside it or widen the envelope in cell.yaml"
                )
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise MotionRejected("target pose's rotation is not a proper rotation matrix (orthonormal, det +1)")
        if self.tool_down_cone_deg is not None:
            # The tool's z axis in the base frame is R's third column; "down" is (0, 0, -1).
            tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, -float(R[2, 2])))))
            if tilt_deg > self.tool_down_cone_deg:
                raise MotionRejected(
                    f"target tool orientation is {tilt_deg:.1f} deg from pointing down, more than the allowed "
                    f"{self.tool_down_cone_deg:.1f} deg; give a pose with the tool pointing down or widen "
                    "tool_down_cone_deg for this robot in cell.yaml"
                )

    def check_linear_speed(self, speed_m_s: float) -> None:
        if not math.isfinite(speed_m_s) or speed_m_s <= 0 or speed_m_s > self.max_linear_speed_m_s:
            raise MotionRejected(
                f"linear speed {speed_m_s} m/s is outside (0, {self.max_linear_speed_m_s}] m/s "
                "(the configured speed limit)"
            )

    def check_duration(self, distance: float, speed: float, unit: str) -> float:
        """The nominal duration (s) of a move of ``distance`` at ``speed``; refused when too long."""
        duration_s = distance / speed
        if not math.isfinite(duration_s) or duration_s > self.max_move_duration_s:
            min_speed = distance / self.max_move_duration_s
            raise MotionRejected(
                f"at {speed:.3g} {unit}/s the move of {distance:.4g} {unit} would take {duration_s:.3g} s, more "
                f"than the {self.max_move_duration_s:.0f} s a move may take; use at least {min_speed:.3g} {unit}/s"
            )
        return duration_s

    def check_joint_speed(self, speed_rad_s: float) -> None:
        if not math.isfinite(speed_rad_s) or speed_rad_s <= 0 or speed_rad_s > self.max_joint_speed_rad_s:
            raise MotionRejected(
                f"joint speed {speed_rad_s} rad/s is outside (0, {self.max_joint_speed_rad_s}] rad/s "
                "(the configured joint speed limit)"
            )

    def check_joints(self, joints_rad: NDArray[np.float64]) -> None:
        q = np.asarray(joints_rad, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(q)):
            raise MotionRejected("joint target contains NaN or infinity")
        if self.joint_limits_rad is None:
            return
        if len(q) != len(self.joint_limits_rad):
            raise MotionRejected(f"joint target has {len(q)} values, the robot has {len(self.joint_limits_rad)}")
        for i, (value, (lo, hi)) in enumerate(zip(q, self.joint_limits_rad, strict=True)):
            if not lo <= value <= hi:
                raise MotionRejected(f"joint {i} target {value:.4f} rad is outside [{lo:.4f}, {hi:.4f}] rad")


# -- protocols ----------------------------------------------------------------------------------


@runtime_checkable
class Camera(Protocol):
    """A camera: open it, grab frames, change exposure/gain/trigger, close it."""

    camera_id: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    def grab(self, timeout_s: float = 2.0) -> Frame: ...
    def set_exposure_us(self, exposure_us: float) -> None: ...
    def set_gain_db(self, gain_db: float) -> None: ...
    def set_trigger(self, mode: str) -> None: ...
    def settings(self) -> dict[str, Any]: ...


@runtime_checkable
class Robot(Protocol):
    """A robot arm: state, linear and joint motion (checked), stop."""

    robot_id: str
    limits: MotionLimits
    motion: MotionOwner

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def state(self) -> RobotState: ...
    def move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float,
                    session: MotionSession | None = None, who: str = "direct") -> None: ...
    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float,
                   session: MotionSession | None = None) -> None: ...
    def stop(self, by: str = "") -> None: ...
    def resume(self, by: str = "") -> bool: ...
    def halt(self) -> None: ...
    def motion_session(self, who: str, what: str) -> contextlib.AbstractContextManager[MotionSession]: ...
    def move_deadline_s(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> float: ...
    def health(self) -> DeviceHealth: ...


@runtime_checkable
class DigitalIO(Protocol):
    """Digital inputs and outputs addressed by channel number."""

    io_id: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    def read_input(self, channel: int) -> bool: ...
    def write_output(self, channel: int, value: bool) -> None: ...


# -- base classes for adapters ------------------------------------------------------------------


class DeviceBase(abc.ABC):
    """Context-manager plumbing shared by adapters: ``with`` opens, ``close()`` is idempotent."""

    def health(self) -> DeviceHealth:
        """The device's availability and outage counters; adapters that count outages override it."""
        return DeviceHealth(available=True)

    def __enter__(self) -> Self:
        self._open_device()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    @abc.abstractmethod
    def _open_device(self) -> None:
        """Open or connect the underlying device."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""


class CameraBase(DeviceBase):
    """Base of camera adapters; ``with cam:`` opens it."""

    def __init__(self, camera_id: str) -> None:
        self.camera_id = camera_id

    def _open_device(self) -> None:
        self.open()

    @abc.abstractmethod
    def open(self) -> None:
        """Open the camera and start acquisition."""

    @abc.abstractmethod
    def grab(self, timeout_s: float = 2.0) -> Frame:
        """Return the newest complete frame; DeviceTimeout when none arrives in time."""

    def set_exposure_us(self, exposure_us: float) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: exposure cannot be set on this camera")

    def set_gain_db(self, gain_db: float) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: gain cannot be set on this camera")

    def set_trigger(self, mode: str) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: trigger mode cannot be set on this camera")

    def settings(self) -> dict[str, Any]:
        return {}


class RobotBase(DeviceBase):
    """Base of robot adapters: the public motion methods own the rules, the adapter fills hooks.

    ``move_linear`` / ``move_joint`` check the envelope, orientation, speed and duration, take the
    robot's motion (``self.motion``: one owner at a time, refused while latched), run the adapter's
    hook under a deadline, and raise ``RobotStopped`` when a Stop halted the move — whatever the
    hook returned. ``stop`` halts and latches; ``resume`` clears the latch; ``halt`` stops motion
    without latching (cleanup after a failed sequence). Adapters implement ``_move_linear``,
    ``_stop`` and may poll ``_motion_aborted()`` while they wait for arrival.
    A controller lost while a move runs or a sequence owns the robot latches it (``_controller_dropped``).
    """

    def __init__(self, robot_id: str, limits: MotionLimits) -> None:
        self.robot_id = robot_id
        self.limits = limits
        self.motion = MotionOwner(robot_id)
        self._move_lock = threading.Lock()
        self._moving_session: MotionSession | None = None

    def _open_device(self) -> None:
        self.connect()

    @abc.abstractmethod
    def connect(self) -> None:
        """Connect to the robot controller."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """The current state; DeviceUnavailable when it is not fresh."""

    # -- motion sessions -----------------------------------------------------------------------------
    @contextlib.contextmanager
    def motion_session(self, who: str, what: str) -> Iterator[MotionSession]:
        """Own the robot's motion for a sequence of moves (``RobotBusy`` / ``RobotStopped`` if not free)."""
        session = self.motion.begin(who, what)
        try:
            yield session
        finally:
            self.motion.end(session)

    def move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float,
                    session: MotionSession | None = None, who: str = "direct") -> None:
        """Move the tool in a straight line to ``T_base_tool`` (metres) at ``speed_m_s``.

        Without ``session`` the move is a sequence of its own (refused while another one runs), owned
        by ``who`` (the motion owner ``GET /robots/{id}/motion`` shows: a token's name).
        """
        target = np.asarray(T_base_tool, dtype=np.float64)
        self.limits.check_pose(target)
        self.limits.check_linear_speed(speed_m_s)
        distance_m = self._distance_to(target)
        nominal_s = self.limits.check_duration(distance_m, speed_m_s, "m")
        self._supervised(session, f"linear move to {_xyz_mm(target)}", nominal_s,
                         lambda: self._move_linear(target, speed_m_s), who)

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float,
                   session: MotionSession | None = None) -> None:
        """Move in joint space to ``joints_rad``; the resulting tool pose is checked too."""
        q = np.asarray(joints_rad, dtype=np.float64)
        self.limits.check_joints(q)
        self.limits.check_joint_speed(speed_rad_s)
        T = self.forward_kinematics(q)
        if T is not None:
            self.limits.check_pose(T)
        span_rad = self._joint_span_to(q)
        nominal_s = self.limits.check_duration(span_rad, speed_rad_s, "rad")
        self._supervised(session, "joint move", nominal_s, lambda: self._move_joint(q, speed_rad_s))

    def move_deadline_s(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> float:
        """How long a linear move to ``T_base_tool`` may take before it is stopped (s)."""
        distance_m = self._distance_to(np.asarray(T_base_tool, dtype=np.float64))
        return move_deadline_s(distance_m / speed_m_s if speed_m_s > 0 else math.inf,
                               self.limits.move_deadline_slack_s)

    def _supervised(self, session: MotionSession | None, what: str, nominal_s: float,
                    hook: Callable[[], None], who: str = "direct") -> None:
        if session is None:
            with self.motion_session(who, what) as own:
                self._run_move(own, nominal_s, hook, in_sequence=False)
        else:
            if not self.motion.is_current(session):
                session.check()
                raise RobotBusy(f"robot {self.robot_id}: {session.what} does not own the robot's motion")
            self._run_move(session, nominal_s, hook, in_sequence=True)

    def _run_move(self, session: MotionSession, nominal_s: float, hook: Callable[[], None], in_sequence: bool) -> None:
        session.check()
        deadline_s = move_deadline_s(nominal_s, self.limits.move_deadline_slack_s)
        timed_out = threading.Event()
        stop_failures: list[BaseException] = []

        def on_deadline() -> None:
            timed_out.set()
            try:
                self._stop()
            except Exception as exc:  # noqa: BLE001 - reported with the timeout below
                stop_failures.append(exc)
                log.error("robot %s: stopping a move past its deadline failed: %s", self.robot_id, exc)

        timer = threading.Timer(deadline_s, on_deadline)
        timer.daemon = True
        dropout_if_lost = in_sequence or self.health().available  # gone before a lone move: an outage only
        with self._move_lock:
            self._moving_session = session
        timer.start()
        try:
            hook()
        except Exception as exc:
            if isinstance(exc, DeviceUnavailable) and dropout_if_lost:
                self._controller_dropped(str(exc))  # latched; the move answers why it failed
                raise
            if session.aborted:
                raise RobotStopped(f"robot {self.robot_id}: the move was stopped ({session.abort_reason})") from exc
            if timed_out.is_set():
                raise self._deadline_error(deadline_s, nominal_s, stop_failures) from exc
            raise
        finally:
            timer.cancel()
            with self._move_lock:
                self._moving_session = None
        if session.aborted:
            # A Stop came while the adapter moved: whatever the adapter says, the move did not happen as asked.
            raise RobotStopped(f"robot {self.robot_id}: the move was stopped ({session.abort_reason})")
        if timed_out.is_set():
            raise self._deadline_error(deadline_s, nominal_s, stop_failures)

    def _deadline_error(self, deadline_s: float, nominal_s: float, stop_failures: list[BaseException]
                        ) -> DeviceTimeout:
        msg = (f"robot {self.robot_id}: the move did not finish within {deadline_s:.1f} s (nominal "
               f"{nominal_s:.1f} s) and was stopped")
        if stop_failures:
            msg += f"; STOPPING IT FAILED: {stop_failures[0]} — check the robot now"
        return DeviceTimeout(msg)

    def _controller_dropped(self, reason: str) -> None:
        """The controller was lost: latch the robot (the Stop's latch) if a move runs or a sequence owns it."""
        session = self.motion.latch_if_owned("controller", f"controller dropped out: {reason}")
        if session is not None:
            log.warning("robot %s: the controller dropped out during %s; latched until an engineer resumes: %s",
                        self.robot_id, session.what, reason)

    def _motion_aborted(self) -> bool:
        """True while the move in progress belongs to a session a Stop has aborted (adapters poll it)."""
        with self._move_lock:
            s = self._moving_session
        return s is not None and s.aborted

    def _distance_to(self, target: NDArray[np.float64]) -> float:
        """Straight-line distance (m) from the current tool position to ``target`` (for the deadline)."""
        try:
            current = self.state().T_base_tool
        except DriverError:
            # Where the tool is now is unknown: the longest move the envelope allows bounds the deadline.
            lim = self.limits
            return 1e-3 * math.dist((lim.x_mm[0], lim.y_mm[0], lim.z_mm[0]), (lim.x_mm[1], lim.y_mm[1], lim.z_mm[1]))
        return float(np.linalg.norm(target[:3, 3] - current[:3, 3]))

    def _joint_span_to(self, q: NDArray[np.float64]) -> float:
        try:
            current = self.state().joints_rad
        except DriverError:
            return 0.0
        if current.shape != q.shape:
            return 0.0
        return float(np.max(np.abs(q - current))) if q.size else 0.0

    # -- conveyor tracking ---------------------------------------------------------------------------
    def start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                       session: MotionSession) -> int:
        """Follow a conveyor from now, as the robot controller does with the belt's encoder wired to it (UR:
        ``conveyor_pulse_decode`` + ``track_conveyor_linear``): every pose commanded from now on is carried
        along ``direction_base`` (unit vector, base frame) by the travel the encoder counts
        (``ticks_per_m``), at most ``most_m`` metres. The count tracking starts at. Needs the motion
        (``session``); a Stop ends tracking at once (the tool stays where it is). ``MotionRejected`` when
        the adapter cannot track."""
        if not self.motion.is_current(session):
            session.check()
            raise RobotBusy(f"robot {self.robot_id}: {session.what} does not own the robot's motion")
        session.check()
        return self._start_tracking(np.asarray(direction_base, dtype=np.float64), float(ticks_per_m), float(most_m))

    def tracks_conveyor(self) -> bool:
        """Whether this adapter can track a conveyor (``start_tracking``); a belt run is refused before the
        robot moves when it cannot."""
        return False

    def stop_tracking(self) -> None:
        """Stop following the conveyor: the tool stays where it is."""
        self._stop_tracking()

    def _start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float) -> int:
        raise MotionRejected(f"robot {self.robot_id}: this adapter cannot track a conveyor (docs/conveyor.md)")

    def _stop_tracking(self) -> None:
        """Tell the controller to stop tracking (nothing when it cannot track)."""

    # -- stop, resume ------------------------------------------------------------------------------
    def stop(self, by: str = "") -> None:
        """Halt now, abort the sequence that owns the robot, and latch until ``resume``.

        The latch holds even when the adapter's stop fails; that failure is raised, never swallowed.
        """
        self.motion.latch(by, "Stop")
        self._stop()

    def resume(self, by: str = "") -> bool:
        """Clear the Stop latch (an engineer's act, ``by`` names them); True when the robot was latched."""
        return self.motion.resume(by)

    def halt(self) -> None:
        """Stop any motion without latching (cleanup after a failed or cancelled sequence)."""
        self._stop()

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """``T_base_tool`` for ``joints_rad`` if the adapter knows it (for the envelope check)."""
        return None

    @abc.abstractmethod
    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        """Send a checked linear move to the controller and wait until it arrives."""

    def _move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None:
        raise MotionRejected(f"robot {self.robot_id}: joint moves are not supported by this adapter")

    @abc.abstractmethod
    def _stop(self) -> None:
        """Tell the controller to stop any motion now."""


def _xyz_mm(T: NDArray[np.float64]) -> str:
    x, y, z = (float(v) * 1000.0 for v in T[:3, 3])
    return f"({x:.1f}, {y:.1f}, {z:.1f}) mm"


class DigitalIOBase(DeviceBase):
    """Base of digital IO adapters."""

    def __init__(self, io_id: str) -> None:
        self.io_id = io_id

    def _open_device(self) -> None:
        self.open()

    @abc.abstractmethod
    def open(self) -> None:
        """Open the IO device."""

    @abc.abstractmethod
    def read_input(self, channel: int) -> bool:
        """Read one digital input."""

    @abc.abstractmethod
    def write_output(self, channel: int, value: bool) -> None:
        """Set one digital output."""
