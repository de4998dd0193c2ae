"""Digital I/O adapters: Modbus TCP coils and inputs (``modbus``), a Robotiq 2F gripper
(``robotiq_gripper``), the virtual cell's gripper (``sim_gripper``) and a serial light controller
(``serial_light``). Each is a ``drivers.base.DigitalIOBase``. Public names are imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from drivers.io.modbus import ModbusDigitalIO, ModbusIOSettings
    from drivers.io.robotiq_gripper import RobotiqGripper, RobotiqGripperSettings
    from drivers.io.serial_light import SerialLightController, SerialLightSettings
    from drivers.io.sim_gripper import SimGripper, SimGripperSettings

__all__ = [
    "ModbusDigitalIO",
    "ModbusIOSettings",
    "RobotiqGripper",
    "RobotiqGripperSettings",
    "SerialLightController",
    "SerialLightSettings",
    "SimGripper",
    "SimGripperSettings",
]

__getattr__ = lazy_getattr(__name__, {
    "ModbusDigitalIO": "drivers.io.modbus",
    "ModbusIOSettings": "drivers.io.modbus",
    "RobotiqGripper": "drivers.io.robotiq_gripper",
    "RobotiqGripperSettings": "drivers.io.robotiq_gripper",
    "SimGripper": "drivers.io.sim_gripper",
    "SimGripperSettings": "drivers.io.sim_gripper",
    "SerialLightController": "drivers.io.serial_light",
    "SerialLightSettings": "drivers.io.serial_light",
})
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""
