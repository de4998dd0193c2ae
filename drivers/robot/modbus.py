"""Robots (or the PLCs in front of them) over Modbus TCP, with a register map in the config (``kind: modbus``).

The register map (``modbus_map.py``) covers:

- pose readback (``actual_pose``: x, y, z, rx, ry, rz, in ``position_unit`` / ``rotation_unit``,
  rotation as fixed-axis XYZ roll-pitch-yaw or as a rotation vector);
- a move request: ``target_pose`` + ``speed`` + a command register, answered through a status
  register (ready / busy / done / error) and an error-code register;
- digital IO (coils out, discrete inputs in);
- a heartbeat both ways: we change ``heartbeat_out_address`` every ``heartbeat_period_s`` (the
  PLC's watchdog), and the PLC's counter at ``heartbeat_in_address`` must keep changing (else the
  robot is reported unavailable: its program is dead even if Modbus still answers).

A poll thread reads the pose, status and inputs at ``poll_hz`` and stamps each sample with the
host time; ``state()`` never does IO and refuses a sample older than ``state_max_age_s``. Lost
connections are reopened with exponential backoff; the outages are counted (``health()``). The
defaults match the simulator in ``drivers/peers/modbus_robot.py``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers import modbus_codec
from drivers.backoff import Backoff, Outages
from drivers.base import (
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    MotionLimits,
    RobotBase,
    RobotState,
)
from drivers.health import DeviceHealth
from drivers.robot.modbus_map import ModbusRobotSettings, RegisterSpec, T_to_registers, registers_to_T

__all__ = ["ModbusRobot", "ModbusRobotSettings", "RegisterSpec"]

@dataclass(frozen=True)
class _Sample:
    host_time_s: float
    pose: tuple[float, ...]
    status: int
    error_code: int
    heartbeat_in: int | None
    digital_in: tuple[bool, ...]
    seq: int


class ModbusRobot(RobotBase):
    """A robot behind a Modbus TCP server, driven through a configurable register map."""

    Settings = ModbusRobotSettings

    def __init__(self, robot_id: str, settings: ModbusRobotSettings | dict[str, Any], limits: MotionLimits) -> None:
        super().__init__(robot_id, limits)
        self.config = (
            settings if isinstance(settings, ModbusRobotSettings) else ModbusRobotSettings.model_validate(settings)
        )
        c = self.config
        self._client = ModbusTcpClient(
            c.host, port=c.port, timeout=c.timeout_s, retries=0, reconnect_delay=0, reconnect_delay_max=0
        )
        self._io_lock = threading.Lock()
        self._sample: _Sample | None = None
        self._sample_cv = threading.Condition()
        self._closing = threading.Event()
        self._poller: threading.Thread | None = None
        self._connected = False
        self._heartbeat_value = 0
        self._heartbeat_sent = 0.0
        self._hb_in_last: int | None = None
        self._hb_in_changed = 0.0
        self._stop_requested = threading.Event()
        self._outages = Outages()
        self._seq = 0

    # -- register codec ------------------------------------------------------------------------------
    def _decode(self, spec: RegisterSpec, regs: list[int]) -> float:
        return modbus_codec.decode(regs, spec.data_type, self.config.word_order, spec.scale)

    def _encode(self, spec: RegisterSpec, value: float) -> list[int]:
        return modbus_codec.encode(value, spec.data_type, self.config.word_order, spec.scale)

    def _pose_to_T(self, v: list[float]) -> NDArray[np.float64]:
        return registers_to_T(v, self.config)

    def _T_to_pose(self, T: NDArray[np.float64]) -> list[float]:
        return T_to_registers(T, self.config)

    # -- Modbus IO (always under _io_lock) -----------------------------------------------------------
    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        with self._io_lock:
            if not self._client.connected and not self._client.connect():
                raise DeviceUnavailable(
                    f"robot {self.robot_id}: cannot connect to Modbus TCP "
                    f"{self.config.host}:{self.config.port}; check address, port and cabling"
                )
            try:
                rr = fn(*args, device_id=self.config.device_id, **kwargs)
            except (ModbusException, OSError) as exc:
                self._client.close()
                raise DeviceUnavailable(
                    f"robot {self.robot_id}: Modbus {what} to {self.config.host}:{self.config.port} failed: {exc}"
                ) from exc
            if rr.isError():
                raise DeviceOperationError(f"robot {self.robot_id}: the device refused Modbus {what}: {rr}")
            return rr

    def _read_regs(self, address: int, count: int) -> list[int]:
        regs: list[int] = self._call(
            f"read of holding registers {address}-{address + count - 1}",
            self._client.read_holding_registers,
            address,
            count=count,
        ).registers
        if len(regs) != count:
            raise DeviceOperationError(
                f"robot {self.robot_id}: asked for {count} registers at {address}, got {len(regs)}: malformed reply"
            )
        return regs

    def _write_regs(self, address: int, values: list[int]) -> None:
        self._call(
            f"write of holding registers {address}-{address + len(values) - 1}",
            self._client.write_registers,
            address,
            values,
        )

    def _read_fields(self, specs: list[RegisterSpec]) -> list[list[int]]:
        lo = min(s.address for s in specs)
        hi = max(s.address + s.width for s in specs)
        if hi - lo <= 125:
            block = self._read_regs(lo, hi - lo)
            return [block[s.address - lo : s.address - lo + s.width] for s in specs]
        return [self._read_regs(s.address, s.width) for s in specs]

    # -- polling ------------------------------------------------------------------------------------------
    def _poll_once(self) -> None:
        c = self.config
        specs = self.config.actual_pose.fields()
        extra = [RegisterSpec(address=c.status_address, data_type="uint16")]
        if c.error_code_address is not None:
            extra.append(RegisterSpec(address=c.error_code_address, data_type="uint16"))
        if c.heartbeat_in_address is not None:
            extra.append(RegisterSpec(address=c.heartbeat_in_address, data_type="uint16"))
        raw = self._read_fields(specs + extra)
        pose = tuple(self._decode(s, r) for s, r in zip(specs, raw[:6], strict=True))
        status = raw[6][0]
        error = raw[7][0] if c.error_code_address is not None else 0
        hb_in = raw[-1][0] if c.heartbeat_in_address is not None else None
        din: tuple[bool, ...] = ()
        if c.digital_in_start is not None and c.digital_count:
            bits = self._call(
                "read of discrete inputs", self._client.read_discrete_inputs, c.digital_in_start, count=c.digital_count
            ).bits
            din = tuple(bool(b) for b in bits[: c.digital_count])
        now = time.time()
        if c.heartbeat_out_address is not None and now - self._heartbeat_sent >= c.heartbeat_period_s:
            self._heartbeat_value = (self._heartbeat_value + 1) & 0xFFFF
            self._write_regs(c.heartbeat_out_address, [self._heartbeat_value])
            self._heartbeat_sent = now
        if hb_in is not None and hb_in != self._hb_in_last:
            self._hb_in_last = hb_in
            self._hb_in_changed = now
        self._seq += 1
        with self._sample_cv:
            self._sample = _Sample(now, pose, status, error, hb_in, din, self._seq)
            self._sample_cv.notify_all()

    def _poll(self) -> None:
        c = self.config
        period = 1.0 / c.poll_hz
        backoff = Backoff(c.reconnect_initial_s, c.reconnect_max_s)
        while not self._closing.is_set():
            t0 = time.monotonic()
            try:
                self._poll_once()
                self._connected = True
                self._outages.up()
                backoff.reset()
                self._closing.wait(max(0.0, period - (time.monotonic() - t0)))
            except Exception as exc:  # a poll thread that dies would serve nothing: every failure is an outage
                self._connected = False
                # an outage counts once, from the first failed poll or stale read until the next good poll
                reason = (str(exc) if isinstance(exc, (DeviceUnavailable, DeviceOperationError))
                          else f"robot {self.robot_id}: unexpected {type(exc).__name__} while polling: {exc}")
                if self._outages.down(reason):  # a request that failed: the controller is lost, not late
                    self._controller_dropped(reason)  # mid-sequence: latched as a Stop latches
                with self._io_lock:
                    self._client.close()
                if self._closing.wait(backoff.next_wait_s()):
                    return
                self._outages.reconnected()

    # -- contract ------------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Start polling and wait for the first sample (at most ``timeout_s`` + one poll)."""
        if self._poller is None:
            self._closing.clear()
            self._poller = threading.Thread(target=self._poll, name=f"modbus-{self.robot_id}", daemon=True)
            self._poller.start()
        deadline = time.monotonic() + self.config.timeout_s + 2.0 / self.config.poll_hz + 0.5
        with self._sample_cv:
            while self._sample is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceUnavailable(
                        f"robot {self.robot_id}: no answer from Modbus TCP {self.config.host}:"
                        f"{self.config.port} ({self._outages.reason}); it keeps retrying in the background"
                    )
                self._sample_cv.wait(remaining)

    def close(self) -> None:
        """Stop polling and close the connection; safe to call twice."""
        self._closing.set()
        if self._poller is not None:
            self._poller.join(timeout=self.config.timeout_s + 2.0)
            self._poller = None
        with self._io_lock:
            self._client.close()
        with self._sample_cv:
            self._sample = None  # a later connect() waits for a new sample

    def _fresh(self) -> _Sample:
        s = self._sample
        now = time.time()
        if s is None:
            raise DeviceUnavailable(
                f"robot {self.robot_id}: no state yet from {self.config.host}:{self.config.port} "
                f"({self._outages.reason})"
            )
        age = now - s.host_time_s
        if age > self.config.state_max_age_s:
            self._outages.down(self._outages.reason or f"state older than {self.config.state_max_age_s} s")
            raise DeviceUnavailable(
                f"robot {self.robot_id}: newest state is {age:.2f} s old (limit "
                f"{self.config.state_max_age_s} s): {self._outages.reason or 'no answer'}; reconnecting"
            )
        if s.heartbeat_in is not None and now - self._hb_in_changed > self.config.heartbeat_timeout_s:
            raise DeviceUnavailable(
                f"robot {self.robot_id}: the controller's heartbeat (register "
                f"{self.config.heartbeat_in_address}) has not changed for "
                f"{now - self._hb_in_changed:.1f} s; its program is not running"
            )
        return s

    def state(self) -> RobotState:
        s = self._fresh()
        c = self.config
        status_name = {
            c.status_ready: "ready",
            c.status_busy: "busy",
            c.status_done: "done",
            c.status_error: "error",
        }.get(s.status, f"status_{s.status}")
        return RobotState(
            T_base_tool=self._pose_to_T(list(s.pose)),
            joints_rad=np.zeros(0),
            timestamp_s=s.host_time_s,
            moving=s.status == c.status_busy,
            mode="error" if s.status == c.status_error else "running",
            metadata={
                "status": status_name,
                "error_code": s.error_code,
                "digital_in": list(s.digital_in),
                "raw_pose": list(s.pose),
            },
        )

    def health(self) -> DeviceHealth:
        try:
            self._fresh()
            available, reason = True, ""
        except DeviceUnavailable as exc:
            available, reason = False, str(exc)
        return self._outages.health(available, reason=reason, last_outage_s=self._outages.last_outage_s)

    def _next_sample(self, after_seq: int, timeout_s: float) -> _Sample:
        deadline = time.monotonic() + timeout_s
        with self._sample_cv:
            while True:
                s = self._sample
                if s is not None and s.seq > after_seq:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._fresh()  # a controller that is gone is DeviceUnavailable, not a slow answer
                    raise DeviceTimeout(f"robot {self.robot_id}: no new state from the controller in {timeout_s} s")
                self._sample_cv.wait(remaining)
        return self._fresh()

    def _error_text(self, code: int) -> str:
        return self.config.error_messages.get(code, f"error code {code}")

    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        c = self.config
        s = self._fresh()
        if s.status == c.status_busy:
            raise DeviceOperationError(f"robot {self.robot_id} is busy with another move; stop() it first")
        if s.status != c.status_ready:  # a finished or failed command still waiting to be cleared
            self._write_regs(c.command_address, [c.clear_value])
            s = self._next_sample(s.seq, c.timeout_s * 2 + 1.0)
        pose = self._T_to_pose(T_base_tool)
        for spec, value in zip(c.target_pose.fields(), pose, strict=True):
            self._write_regs(spec.address, self._encode(spec, value))
        speed = speed_m_s * (1000.0 if c.speed_unit == "mm/s" else 1.0)
        self._write_regs(c.speed.address, self._encode(c.speed, speed))
        dist_m = float(np.linalg.norm(T_base_tool[:3, 3] - self._pose_to_T(list(s.pose))[:3, 3]))
        timeout_s = dist_m / speed_m_s + c.move_timeout_margin_s
        self._stop_requested.clear()
        self._write_regs(c.command_address, [c.move_value])
        if self._motion_aborted():  # a Stop raced the command: the controller must not keep moving
            self._stop()
        seq = self._sample.seq if self._sample is not None else 0
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                s = self._next_sample(seq, c.state_max_age_s + c.timeout_s)
                seq = s.seq
                if s.status == c.status_error:
                    raise DeviceOperationError(
                        f"robot {self.robot_id}: the controller refused or aborted the move: "
                        f"{self._error_text(s.error_code)}"
                    )
                if s.status == c.status_done:
                    if self._stop_requested.is_set():
                        raise DeviceOperationError(f"robot {self.robot_id}: the move was stopped before it arrived")
                    return
                if time.monotonic() > deadline:
                    with contextlib.suppress(DeviceUnavailable, DeviceOperationError):
                        self._write_regs(c.command_address, [c.stop_value])
                    raise DeviceTimeout(
                        f"robot {self.robot_id}: the move did not finish within {timeout_s:.1f} s; a stop was sent"
                    )
        finally:
            with contextlib.suppress(DeviceUnavailable, DeviceOperationError, DeviceTimeout):
                self._write_regs(c.command_address, [c.clear_value])
                self._next_sample(self._sample.seq if self._sample is not None else 0, c.timeout_s + 0.5)

    def _stop(self) -> None:
        """Write the stop command."""
        self._stop_requested.set()
        self._write_regs(self.config.command_address, [self.config.stop_value])

    def set_digital_out(self, channel: int, value: bool) -> None:
        c = self.config
        if c.digital_out_coil_start is None or not 0 <= channel < c.digital_count:
            raise DeviceOperationError(
                f"robot {self.robot_id}: digital output {channel} is not configured (0..{c.digital_count - 1})"
            )
        self._call(
            f"write of coil {c.digital_out_coil_start + channel}",
            self._client.write_coil,
            c.digital_out_coil_start + channel,
            bool(value),
        )
