"""The driver contract in one import: device Protocols, the values that cross them, the bases of
adapters and the typed errors (``from drivers.base import Robot, RobotBase, MotionLimits, ...``).

Each lives in the module of its job; this module only re-exports them:

- ``drivers.protocols``: ``Camera``, ``Robot``, ``DigitalIO`` — what code that *uses* devices depends on;
- ``drivers.values``: ``Frame``, ``RobotState``;
- ``drivers.limits``: ``MotionLimits`` (the envelope, orientation cone, speed and duration checks);
- ``drivers.device_base``: ``DeviceBase``, ``CameraBase``, ``DigitalIOBase``;
- ``drivers.robot_base``: ``RobotBase`` — its public ``move_linear`` / ``move_joint`` run the one
  envelope and speed check and only then call the adapter's hooks, so no adapter can bypass it;
- ``drivers.errors`` (the errors) and ``drivers.motion`` (the motion owner and the Stop latch).

Units: poses are ``T_base_tool`` 4x4 in metres; joints in radians; speeds in m/s (linear) and
rad/s (joint); envelopes in millimetres, as the config states them (``*_mm``).
"""

from __future__ import annotations

from drivers.device_base import CameraBase, DeviceBase, DigitalIOBase
from drivers.errors import (
    DeviceInitError,
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    DriverError,
    MotionRejected,
)
from drivers.limits import MotionLimits
from drivers.motion import MotionOwner, MotionSession, RobotBusy, RobotStopped
from drivers.protocols import Camera, DigitalIO, Robot
from drivers.robot_base import RobotBase
from drivers.values import Frame, RobotState

__all__ = [
    "Camera", "CameraBase", "DeviceBase", "DeviceInitError", "DeviceOperationError", "DeviceTimeout",
    "DeviceUnavailable", "DigitalIO", "DigitalIOBase", "DriverError", "Frame", "MotionLimits", "MotionOwner",
    "MotionRejected", "MotionSession", "Robot", "RobotBase", "RobotBusy", "RobotState", "RobotStopped",
]
