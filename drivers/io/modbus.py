"""Digital IO over Modbus TCP: coils are outputs, discrete inputs are inputs (``kind: modbus``).

Each call is one Modbus request with a deadline (``timeout_s``); a lost connection is reopened
on the next call, at most once per ``reconnect_interval_s``, and the outages are counted.
"""

from __future__ import annotations

import threading
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers.backoff import Backoff, Outages
from drivers.base import DeviceOperationError, DeviceUnavailable, DigitalIOBase
from drivers.health import DeviceHealth


class ModbusIOSettings(BaseModel):
    """Where the IO lives on a Modbus TCP device."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field(min_length=1)
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    timeout_s: float = Field(1.0, gt=0, le=60)
    output_coil_start: int = Field(0, ge=0, le=65535, description="coil address of output channel 0")
    input_start: int = Field(0, ge=0, le=65535, description="discrete-input address of input channel 0")
    outputs: int = Field(8, ge=0, le=2000)
    inputs: int = Field(8, ge=0, le=2000)
    reconnect_interval_s: float = Field(0.5, gt=0, le=600)


class ModbusDigitalIO(DigitalIOBase):
    """Digital inputs and outputs of a Modbus TCP device (a PLC, a remote IO block)."""

    Settings = ModbusIOSettings

    def __init__(self, io_id: str, settings: ModbusIOSettings | dict[str, Any]) -> None:
        super().__init__(io_id)
        self.config = settings if isinstance(settings, ModbusIOSettings) else ModbusIOSettings.model_validate(settings)
        c = self.config
        self._client = ModbusTcpClient(
            c.host, port=c.port, timeout=c.timeout_s, retries=0, reconnect_delay=0, reconnect_delay_max=0
        )
        self._lock = threading.Lock()
        # a fixed interval: Backoff with the same start and cap
        self._backoff = Backoff(c.reconnect_interval_s, c.reconnect_interval_s)
        self._outages = Outages()

    def open(self) -> None:
        with self._lock:
            self._ensure_connected(force=True)

    def _ensure_connected(self, force: bool = False) -> None:
        if self._client.connected:
            return
        if not force and not self._backoff.due():
            raise DeviceUnavailable(
                f"io {self.io_id}: Modbus TCP {self.config.host}:{self.config.port} is not reachable; retrying shortly"
            )
        self._backoff.schedule()
        if not self._client.connect():
            self._outages.down(f"cannot connect to {self.config.host}:{self.config.port}")
            raise DeviceUnavailable(
                f"io {self.io_id}: cannot connect to Modbus TCP {self.config.host}:"
                f"{self.config.port}; check address, port and cabling"
            )
        self._outages.up()

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            self._ensure_connected()
            try:
                rr = fn(*args, device_id=self.config.device_id, **kwargs)
            except (ModbusException, OSError) as exc:
                self._client.close()
                self._outages.down(f"Modbus {what} failed: {exc}")
                raise DeviceUnavailable(
                    f"io {self.io_id}: Modbus {what} on {self.config.host}:{self.config.port} failed: {exc}"
                ) from exc
        if rr.isError():
            raise DeviceOperationError(f"io {self.io_id}: the device refused Modbus {what}: {rr}")
        return rr

    def read_input(self, channel: int) -> bool:
        if not 0 <= channel < self.config.inputs:
            raise DeviceOperationError(f"io {self.io_id}: input {channel} is not in 0..{self.config.inputs - 1}")
        address = self.config.input_start + channel
        bits = self._call(f"read of discrete input {address}", self._client.read_discrete_inputs, address, count=1).bits
        if not bits:
            raise DeviceOperationError(f"io {self.io_id}: empty reply reading discrete input {address}")
        return bool(bits[0])

    def write_output(self, channel: int, value: bool) -> None:
        if not 0 <= channel < self.config.outputs:
            raise DeviceOperationError(f"io {self.io_id}: output {channel} is not in 0..{self.config.outputs - 1}")
        address = self.config.output_coil_start + channel
        self._call(f"write of coil {address}", self._client.write_coil, address, bool(value))

    def read_output(self, channel: int) -> bool:
        address = self.config.output_coil_start + channel
        return bool(self._call(f"read of coil {address}", self._client.read_coils, address, count=1).bits[0])

    def close(self) -> None:
        with self._lock:
            self._client.close()

    def health(self) -> DeviceHealth:
        return self._outages.health(self._client.connected and self._outages.is_up)
