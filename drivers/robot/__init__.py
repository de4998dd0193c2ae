"""Robot adapters: the virtual cell's real-time robot (``sim``), Universal Robots through
ur_rtde (``ur_rtde``, its state and control links in ``ur_rtde_link``/``ur_rtde_worker``), and a
robot behind Modbus TCP registers (``modbus``, its register map ``modbus_map``). Each is a
``drivers.base.RobotBase``; the motion owner and the Stop latch are ``drivers.motion``. Public names are
imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from drivers.robot.modbus import ModbusRobot
    from drivers.robot.modbus_map import ModbusRobotSettings
    from drivers.robot.sim import SimRobot, SimRobotSettings
    from drivers.robot.ur_rtde import URRTDERobot
    from drivers.robot.ur_rtde_settings import URRTDESettings

__all__ = [
    "ModbusRobot",
    "ModbusRobotSettings",
    "SimRobot",
    "SimRobotSettings",
    "URRTDERobot",
    "URRTDESettings",
]

__getattr__ = lazy_getattr(__name__, {
    "SimRobot": "drivers.robot.sim",
    "SimRobotSettings": "drivers.robot.sim",
    "URRTDERobot": "drivers.robot.ur_rtde",
    "URRTDESettings": "drivers.robot.ur_rtde_settings",
    "ModbusRobot": "drivers.robot.modbus",
    "ModbusRobotSettings": "drivers.robot.modbus_map",
})
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""
