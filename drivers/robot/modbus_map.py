"""The register map of a Modbus TCP robot (``kind: modbus``): its settings and pose conversions.

The map names, for each value, its register address, data type (``int16``, ``uint16``,
``int32``, ``uint32``, ``float32``; 32-bit values in the configured word order) and scale
(engineering value = raw value x scale, in the unit the map states). Poses are in
``position_unit`` / ``rotation_unit``, rotation as fixed-axis XYZ roll-pitch-yaw or as a
rotation vector. The defaults match the simulator in ``drivers/peers/modbus_robot.py``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

from drivers.modbus_codec import WIDTH, DataTypeName, WordOrder


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RegisterSpec(_Strict):
    """One value in holding registers."""

    address: int = Field(ge=0, le=65535)
    data_type: DataTypeName = "float32"
    scale: float = Field(1.0, description="engineering value = raw register value x scale")

    @property
    def width(self) -> int:
        return WIDTH[self.data_type]


def _f(address: int) -> RegisterSpec:
    return RegisterSpec(address=address)


class PoseRegisters(_Strict):
    x: RegisterSpec
    y: RegisterSpec
    z: RegisterSpec
    rx: RegisterSpec
    ry: RegisterSpec
    rz: RegisterSpec

    def fields(self) -> list[RegisterSpec]:
        return [self.x, self.y, self.z, self.rx, self.ry, self.rz]


def _pose_map(start: int) -> PoseRegisters:
    return PoseRegisters(
        x=_f(start), y=_f(start + 2), z=_f(start + 4), rx=_f(start + 6), ry=_f(start + 8), rz=_f(start + 10)
    )


class ModbusRobotSettings(_Strict):
    """Connection, register map and handshake of a Modbus TCP robot."""

    host: str = Field(min_length=1)
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    word_order: WordOrder = Field("big", description="order of the two 16-bit words of 32-bit values")
    timeout_s: float = Field(1.0, gt=0, le=60, description="deadline of one Modbus request")
    poll_hz: float = Field(50.0, gt=0, le=1000)
    state_max_age_s: float = Field(0.5, gt=0, le=60)
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)
    position_unit: Literal["mm", "m"] = "mm"
    rotation_unit: Literal["deg", "rad"] = "deg"
    rotation_form: Literal["rpy_xyz", "rotvec"] = Field(
        "rpy_xyz", description="fixed-axis XYZ roll/pitch/yaw or rotation vector"
    )
    actual_pose: PoseRegisters = Field(default_factory=lambda: _pose_map(0))
    target_pose: PoseRegisters = Field(default_factory=lambda: _pose_map(20))
    speed: RegisterSpec = Field(default_factory=lambda: _f(32))
    speed_unit: Literal["mm/s", "m/s"] = "mm/s"
    command_address: int = Field(40, ge=0, le=65535)
    move_value: int = 1
    stop_value: int = 2
    clear_value: int = 0
    status_address: int = Field(41, ge=0, le=65535)
    status_ready: int = 0
    status_busy: int = 1
    status_done: int = 2
    status_error: int = 3
    error_code_address: int | None = Field(42, ge=0, le=65535)
    error_messages: dict[int, str] = Field(
        default_factory=lambda: {
            1: "target out of reach",
            2: "watchdog expired (heartbeat lost)",
            3: "unknown command",
            4: "bad speed",
        }
    )
    heartbeat_out_address: int | None = Field(50, ge=0, le=65535)
    heartbeat_period_s: float = Field(0.2, gt=0, le=60)
    heartbeat_in_address: int | None = Field(51, ge=0, le=65535)
    heartbeat_timeout_s: float = Field(1.0, gt=0, le=60, description="PLC counter unchanged this long: dead")
    digital_out_coil_start: int | None = Field(0, ge=0, le=65535)
    digital_in_start: int | None = Field(0, ge=0, le=65535)
    digital_count: int = Field(8, ge=0, le=64)
    move_timeout_margin_s: float = Field(5.0, gt=0, le=600, description="added to distance/speed")

    @model_validator(mode="after")
    def _heartbeat(self) -> ModbusRobotSettings:
        if self.heartbeat_timeout_s <= 1.0 / self.poll_hz:
            raise ValueError("heartbeat_timeout_s must be longer than one poll period (1 / poll_hz)")
        return self




def registers_to_T(values: list[float], c: ModbusRobotSettings) -> NDArray[np.float64]:
    """``T_base_tool`` (4x4, metres) from a pose in the map's units and rotation form."""
    p = np.array(values[:3]) * (1e-3 if c.position_unit == "mm" else 1.0)
    ang = np.array(values[3:]) * (math.pi / 180.0 if c.rotation_unit == "deg" else 1.0)
    R = Rotation.from_euler("xyz", ang) if c.rotation_form == "rpy_xyz" else Rotation.from_rotvec(ang)
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    T[:3, 3] = p
    return T


def T_to_registers(T: NDArray[np.float64], c: ModbusRobotSettings) -> list[float]:
    """A pose in the map's units and rotation form from ``T_base_tool`` (4x4, metres)."""
    R = Rotation.from_matrix(T[:3, :3])
    ang = R.as_euler("xyz") if c.rotation_form == "rpy_xyz" else R.as_rotvec()
    ang = ang * (180.0 / math.pi if c.rotation_unit == "deg" else 1.0)
    p = T[:3, 3] * (1e3 if c.position_unit == "mm" else 1.0)
    return [float(x) for x in (*p, *ang)]
