"""Robot adapters: the virtual cell's real-time robot (``sim``), Universal Robots through
ur_rtde (``ur_rtde``, its state and control links in ``ur_rtde_link``/``ur_rtde_worker``), and a
robot behind Modbus TCP registers (``modbus``, its register map ``modbus_map``). Each is a
``drivers.base.RobotBase``; the motion owner and the Stop latch are ``drivers.motion``. Public names are
imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.robot.modbus import ModbusRobot
    from drivers.robot.modbus_map import ModbusRobotSettings
    from drivers.robot.sim import SimRobot, SimRobotSettings
    from drivers.robot.ur_rtde import URRTDERobot, URRTDESettings

_LAZY: dict[str, str] = {
    "SimRobot": "drivers.robot.sim",
    "SimRobotSettings": "drivers.robot.sim",
    "URRTDERobot": "drivers.robot.ur_rtde",
    "URRTDESettings": "drivers.robot.ur_rtde",
    "ModbusRobot": "drivers.robot.modbus",
    "ModbusRobotSettings": "drivers.robot.modbus_map",
}
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""

__all__ = [
    "ModbusRobot",
    "ModbusRobotSettings",
    "SimRobot",
    "SimRobotSettings",
    "URRTDERobot",
    "URRTDESettings",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
