"""Robotiq-style 2-finger grippers over Modbus RTU (``kind: robotiq_gripper``).

Robotiq's register map: the action request, position, speed and force go to holding registers
1000-1002; the status (activated, moving, object detected), fault, position and current come back
from input registers 2000-2002 (see ``drivers/peers/robotiq_gripper.py`` for the bytes).

Gripper API: ``activate()``, ``open_gripper()``, ``close_gripper()``, ``move(position, ...)``
(0 open .. 255 closed), ``status()``. As a digital IO device, output 0 closes (True) or opens
(False) the gripper and input 0 reads "object detected".

Every Modbus request has a deadline (``timeout_s``); a serial port that disappears is reopened on
the next call (rate-limited by the backoff) and the outages are counted (``health()``).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ModbusException

from drivers.backoff import Backoff, Outages
from drivers.base import DeviceOperationError, DeviceTimeout, DeviceUnavailable, DigitalIOBase
from drivers.health import DeviceHealth

OUT_BASE = 1000
IN_BASE = 2000
FAULTS = {
    0x05: "action delayed: the activation must complete first",
    0x07: "the activation bit is not set",
    0x08: "maximum operating temperature exceeded",
    0x09: "no communication for at least 1 s",
    0x0A: "under minimum operating voltage",
    0x0B: "automatic release in progress",
    0x0C: "internal fault",
    0x0D: "activation fault, verify that no interference or other error occurred",
    0x0E: "overcurrent triggered",
    0x0F: "automatic release completed",
}


class RobotiqGripperSettings(BaseModel):
    """Serial line and motion defaults of the gripper."""

    model_config = ConfigDict(extra="forbid")

    port: str = Field(min_length=1, description="serial device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(115200, ge=1200, le=1_000_000)
    device_id: int = Field(9, ge=1, le=247)
    timeout_s: float = Field(0.5, gt=0, le=30, description="deadline of one Modbus request")
    speed_percent: float = Field(50.0, ge=0, le=100)
    force_percent: float = Field(50.0, ge=0, le=100)
    activation_timeout_s: float = Field(5.0, gt=0, le=60)
    move_timeout_s: float = Field(5.0, gt=0, le=60)
    activate_on_open: bool = True
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)


def _byte(percent: float) -> int:
    return max(0, min(255, round(percent / 100.0 * 255)))


class RobotiqGripper(DigitalIOBase):
    """A Robotiq 2F-style gripper on Modbus RTU."""

    Settings = RobotiqGripperSettings

    def __init__(self, io_id: str, settings: RobotiqGripperSettings | dict[str, Any]) -> None:
        super().__init__(io_id)
        self.config = (
            settings
            if isinstance(settings, RobotiqGripperSettings)
            else RobotiqGripperSettings.model_validate(settings)
        )
        c = self.config
        self._client = ModbusSerialClient(
            c.port, baudrate=c.baudrate, timeout=c.timeout_s, retries=0, reconnect_delay=0, reconnect_delay_max=0
        )
        self._lock = threading.Lock()
        self._outages = Outages()
        self._outages.reason = "not opened"
        self._backoff = Backoff(c.reconnect_initial_s, c.reconnect_max_s)

    # -- Modbus ---------------------------------------------------------------------------------------
    def _fail(self, reason: str) -> None:
        self._outages.down(reason)

    def _connect(self, force: bool = False) -> None:
        if self._client.connected:
            return
        if not force and not self._backoff.due():
            raise DeviceUnavailable(
                f"io {self.io_id}: gripper port {self.config.port} is unavailable "
                f"({self._outages.reason}); next attempt in {self._backoff.remaining_s():.1f} s"
            )
        if not self._client.connect():
            self._backoff.schedule()
            self._fail(f"cannot open {self.config.port}")
            raise DeviceUnavailable(
                f"io {self.io_id}: cannot open serial port {self.config.port}; check the cable, "
                "the USB adapter and the permissions (group dialout)"
            )
        if not force:
            self._outages.reconnected()
        self._backoff.reset()

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            self._connect()
            try:
                rr = fn(*args, device_id=self.config.device_id, **kwargs)
            except (ModbusException, OSError) as exc:
                self._client.close()
                self._fail(f"{what} failed: {exc}")
                if "No response" in str(exc) or "timeout" in str(exc).lower():
                    raise DeviceTimeout(
                        f"io {self.io_id}: the gripper did not answer {what} within "
                        f"{self.config.timeout_s} s; check power, baud rate ({self.config.baudrate}) "
                        f"and device id ({self.config.device_id})"
                    ) from exc
                raise DeviceUnavailable(f"io {self.io_id}: {what} on {self.config.port} failed: {exc}") from exc
            if rr.isError():
                self._outages.up()
                raise DeviceOperationError(f"io {self.io_id}: the gripper refused {what}: {rr}")
            self._outages.up()
            return rr

    def _write(self, action: int, position: int, speed: int, force: int) -> None:
        self._call(
            "the command write",
            self._client.write_registers,
            OUT_BASE,
            [action << 8, position & 0xFF, (speed << 8) | force],
        )

    def status(self) -> dict[str, Any]:
        """Activation, motion, object detection, fault, position (0..255) and current."""
        regs = self._call("the status read", self._client.read_input_registers, IN_BASE, count=3).registers
        if len(regs) != 3:
            raise DeviceOperationError(f"io {self.io_id}: malformed status reply {regs!r}")
        st, fault, pos = regs[0] >> 8, regs[1] >> 8, regs[2] >> 8
        obj = (st >> 6) & 0x3
        return {
            "activated": (st >> 4) & 0x3 == 3,
            "activating": (st >> 4) & 0x3 == 1,
            "go_to": bool(st & 0x08),
            "moving": obj == 0 and bool(st & 0x08),
            "object_detected": obj in (1, 2),
            "at_position": obj == 3,
            "fault": fault,
            "fault_text": FAULTS.get(fault, ""),
            "position_request": regs[1] & 0xFF,
            "position": pos,
            "current": regs[2] & 0xFF,
        }

    # -- gripper API ------------------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            self._connect(force=True)
        if self.config.activate_on_open:
            self.activate()

    def activate(self) -> None:
        """Reset and activate (the fingers calibrate); waits until the gripper reports active."""
        if self.status()["activated"]:
            return
        self._write(0x00, 0, 0, 0)
        self._write(0x01, 0, 0, 0)
        deadline = time.monotonic() + self.config.activation_timeout_s
        while True:
            s = self.status()
            if s["activated"]:
                return
            if s["fault"] not in (0,):
                raise DeviceOperationError(
                    f"io {self.io_id}: activation failed: fault 0x{s['fault']:02X} {s['fault_text']}"
                )
            if time.monotonic() > deadline:
                raise DeviceTimeout(
                    f"io {self.io_id}: the gripper did not finish activating within "
                    f"{self.config.activation_timeout_s} s"
                )
            time.sleep(0.02)

    def move(
        self, position: int, speed_percent: float | None = None, force_percent: float | None = None, wait: bool = True
    ) -> dict[str, Any]:
        """Go to ``position`` (0 open .. 255 closed); with ``wait``, return the final status."""
        if not 0 <= position <= 255:
            raise DeviceOperationError(f"io {self.io_id}: position {position} is not in 0..255")
        c = self.config
        speed = _byte(c.speed_percent if speed_percent is None else speed_percent)
        force = _byte(c.force_percent if force_percent is None else force_percent)
        self._write(0x09, position, speed, force)  # rACT + rGTO
        if not wait:
            return self.status()
        deadline = time.monotonic() + c.move_timeout_s
        time.sleep(0.01)
        while True:
            s = self.status()
            if s["fault"]:
                raise DeviceOperationError(
                    f"io {self.io_id}: the gripper refused the move: fault 0x{s['fault']:02X} {s['fault_text']}"
                )
            if s["position_request"] == position and (s["at_position"] or s["object_detected"]):
                return s
            if time.monotonic() > deadline:
                raise DeviceTimeout(
                    f"io {self.io_id}: the gripper did not reach {position} within "
                    f"{c.move_timeout_s} s (now at {s['position']})"
                )
            time.sleep(0.01)

    def open_gripper(self, **kw: Any) -> dict[str, Any]:
        return self.move(0, **kw)

    def close_gripper(self, **kw: Any) -> dict[str, Any]:
        return self.move(255, **kw)

    # -- DigitalIO contract -----------------------------------------------------------------------------
    def write_output(self, channel: int, value: bool) -> None:
        if channel != 0:
            raise DeviceOperationError(f"io {self.io_id}: the gripper has one output (0: close/open), not {channel}")
        self.move(255 if value else 0)

    def read_input(self, channel: int) -> bool:
        if channel != 0:
            raise DeviceOperationError(
                f"io {self.io_id}: the gripper has one input (0: object detected), not {channel}"
            )
        return bool(self.status()["object_detected"])

    def close(self) -> None:
        with self._lock:
            self._client.close()

    def health(self) -> DeviceHealth:
        return self._outages.health(self._outages.is_up)
