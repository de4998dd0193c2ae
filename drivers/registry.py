"""Adapter registry: the config's ``kind:`` string to the adapter class, imported only when used.

Each adapter class carries a pydantic ``Settings`` model for its own settings. Constructors:
cameras ``cls(camera_id, settings)``, robots ``cls(robot_id, settings, limits)``, IO devices
``cls(io_id, settings)``, conveyors ``cls(conveyor_id, settings)``. An adapter whose optional system
library is missing fails when it is built, with a message naming what to install, never at import
of this module.
"""

from __future__ import annotations

import importlib
from typing import Final, Literal

from drivers.base import DeviceInitError

Category = Literal["camera", "robot", "io", "conveyor"]

ADAPTERS: Final[dict[Category, dict[str, tuple[str, str]]]] = {
    "camera": {
        "sim": ("drivers.camera.sim", "SimCamera"),
        "replay": ("drivers.replay", "ReplayCamera"),
        "opencv": ("drivers.camera.opencv", "OpenCVCamera"),
        "aravis": ("drivers.camera.aravis", "AravisCamera"),
    },
    "robot": {
        "sim": ("drivers.robot.sim", "SimRobot"),
        "replay": ("drivers.replay", "ReplayRobot"),
        "ur_rtde": ("drivers.robot.ur_rtde", "URRTDERobot"),
        "modbus": ("drivers.robot.modbus", "ModbusRobot"),
    },
    "io": {
        "modbus": ("drivers.io.modbus", "ModbusDigitalIO"),
        "serial_light": ("drivers.io.serial_light", "SerialLightController"),
        "robotiq_gripper": ("drivers.io.robotiq_gripper", "RobotiqGripper"),
        "sim_gripper": ("drivers.io.sim_gripper", "SimGripper"),
    },
    "conveyor": {
        "sim_conveyor": ("drivers.conveyor.sim", "SimConveyor"),
    },
}


class UnknownAdapter(DeviceInitError, ValueError):
    """The config names a ``kind`` no adapter is registered for."""


def kinds(category: Category) -> list[str]:
    """The ``kind`` names known for a device category."""
    return sorted(ADAPTERS[category])


def adapter_class(category: Category, kind: str) -> type:
    """Import and return the adapter class registered for ``kind``."""
    try:
        module_name, class_name = ADAPTERS[category][kind]
    except KeyError:
        raise UnknownAdapter(
            f"unknown {category} kind {kind!r}; known kinds: {', '.join(kinds(category)) or 'none'}"
        ) from None
    module = importlib.import_module(module_name)
    cls: type = getattr(module, class_name)
    return cls
