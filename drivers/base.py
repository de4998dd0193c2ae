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
import math
import time
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import NDArray

# -- errors -------------------------------------------------------------------------------------


class DriverError(Exception):
    """Root of every driver error. Messages say what failed and what to do about it."""


class DeviceUnavailable(DriverError, ConnectionError):
    """The device cannot be reached (not connected, unplugged, peer gone)."""


class DeviceInitError(DriverError):
    """The device was reached but could not be set up (bad setting, missing feature or library)."""


class DeviceOperationError(DriverError):
    """A command to a working device failed (malformed reply, rejected command)."""


class DeviceTimeout(DriverError, TimeoutError):
    """The device did not answer in time."""


class MotionRejected(DriverError, ValueError):
    """A commanded motion was refused before it was sent (envelope, speed, not allowed)."""


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

    def check_linear_speed(self, speed_m_s: float) -> None:
        if not math.isfinite(speed_m_s) or speed_m_s <= 0 or speed_m_s > self.max_linear_speed_m_s:
            raise MotionRejected(
                f"linear speed {speed_m_s} m/s is outside (0, {self.max_linear_speed_m_s}] m/s "
                "(the configured speed limit)"
            )

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

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def state(self) -> RobotState: ...
    def move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None: ...
    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None: ...
    def stop(self) -> None: ...


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
    """Base of robot adapters. The public motion methods check limits, then call the hooks."""

    def __init__(self, robot_id: str, limits: MotionLimits) -> None:
        self.robot_id = robot_id
        self.limits = limits

    def _open_device(self) -> None:
        self.connect()

    @abc.abstractmethod
    def connect(self) -> None:
        """Connect to the robot controller."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """The current state; DeviceUnavailable when it is not fresh."""

    def move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        """Move the tool in a straight line to ``T_base_tool`` (metres) at ``speed_m_s``."""
        target = np.asarray(T_base_tool, dtype=np.float64)
        self.limits.check_pose(target)
        self.limits.check_linear_speed(speed_m_s)
        self._move_linear(target, speed_m_s)

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None:
        """Move in joint space to ``joints_rad``; the resulting tool pose is checked too."""
        q = np.asarray(joints_rad, dtype=np.float64)
        self.limits.check_joints(q)
        self.limits.check_joint_speed(speed_rad_s)
        T = self.forward_kinematics(q)
        if T is not None:
            self.limits.check_pose(T)
        self._move_joint(q, speed_rad_s)

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """``T_base_tool`` for ``joints_rad`` if the adapter knows it (for the envelope check)."""
        return None

    @abc.abstractmethod
    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        """Send a checked linear move to the controller."""

    def _move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None:
        raise MotionRejected(f"robot {self.robot_id}: joint moves are not supported by this adapter")

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now."""


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
