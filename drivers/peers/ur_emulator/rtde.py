"""The controller's side of RTDE (port 30004): recipes, start/pause, data packages, inputs.

Protocol version ``V``, controller version ``v``, output/input recipe setup ``O``/``I``, start
``S``, pause ``P`` and data packages ``U``; big-endian; outputs at up to the controller's rate
(500 Hz, an e-Series controller, version 5.11). Variable names and types are the controller's. An
input variable has one writer: the client that set it up first, until it disconnects (``IN_USE``
to the others), so a second control client cannot write the first one's command register.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
from collections.abc import Callable
from typing import Any

from drivers.peers.ur_emulator.arm import SAFETY_PROTECTIVE_STOP, T_to_pose
from drivers.peers.ur_emulator.controller import Controller

log = logging.getLogger("cellctl.ur_emulator")

CONTROLLER_VERSION = (5, 11, 1, 108318)

_STRUCT = {"DOUBLE": "d", "UINT64": "Q", "UINT32": "I", "INT32": "i", "UINT8": "B", "BOOL": "?",
           "VECTOR6D": "6d", "VECTOR3D": "3d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}

VARIABLE_TYPES: dict[str, str] = {
    **{n: "DOUBLE" for n in (
        "timestamp", "actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
        "actual_main_voltage", "actual_robot_voltage", "actual_robot_current", "standard_analog_input0",
        "standard_analog_input1", "standard_analog_output0", "standard_analog_output1", "tool_analog_input0",
        "tool_analog_input1", "tool_output_current", "tool_temperature", "payload", "speed_slider_fraction",
        "standard_analog_output_0", "standard_analog_output_1", "io_current", "euromap67_24V_voltage",
        "euromap67_24V_current", "actual_tool_flange_pose_placeholder")},
    **{n: "VECTOR6D" for n in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
        "actual_current", "joint_control_output", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force",
        "target_TCP_pose", "target_TCP_speed", "joint_temperatures", "actual_joint_voltage",
        "ft_raw_wrench", "payload_inertia", "tcp_offset", "actual_current_as_torque", "external_force_torque",
        "actual_current_window", "target_current_window")},
    **{n: "VECTOR3D" for n in (
        "actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity")},
    **{n: "UINT64" for n in ("actual_digital_input_bits", "actual_digital_output_bits")},
    **{n: "UINT32" for n in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "tool_analog_input_types",
        "euromap67_input_bits", "euromap67_output_bits", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63", "input_bit_registers0_to_31", "input_bit_registers32_to_63",
        "speed_slider_mask", "script_control_line", "actual_robot_energy_consumed")},
    **{n: "INT32" for n in (
        "robot_mode", "safety_mode", "safety_status", "tool_mode", "tool_output_voltage")},
    "joint_mode": "VECTOR6INT32",
    **{n: "UINT8" for n in (
        "tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode",
        "standard_digital_output_mask", "standard_digital_output", "configurable_digital_output_mask",
        "configurable_digital_output", "tool_digital_output_mask", "tool_digital_output",
        "standard_analog_output_mask", "standard_analog_output_type")},
}
for _i in range(48):
    VARIABLE_TYPES[f"output_int_register_{_i}"] = "INT32"
    VARIABLE_TYPES[f"input_int_register_{_i}"] = "INT32"
    VARIABLE_TYPES[f"output_double_register_{_i}"] = "DOUBLE"
    VARIABLE_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    VARIABLE_TYPES[f"input_bit_register_{_i}"] = "BOOL"
    VARIABLE_TYPES[f"output_bit_register_{_i}"] = "BOOL"

_VALUES: dict[str, Callable[[Controller, float], Any]] = {
    "timestamp": lambda c, now: now - c.t_start,
    **dict.fromkeys(("actual_q", "target_q"), lambda c, now: tuple(c.arm.q)),
    **dict.fromkeys(("actual_TCP_pose", "target_TCP_pose"), lambda c, now: tuple(T_to_pose(c.arm.T))),
    **dict.fromkeys(("actual_TCP_speed", "target_TCP_speed"), lambda c, now: c.arm.tcp_speed(now)),
    **dict.fromkeys(("actual_qd", "target_qd"), lambda c, now: c.arm.joint_speeds(now)),
    "robot_mode": lambda c, now: c.arm.robot_mode,
    **dict.fromkeys(("safety_mode", "safety_status"), lambda c, now: c.arm.safety_mode),
    "robot_status_bits": lambda c, now: c.robot_status_bits(),
    "safety_status_bits": lambda c, now: (1 << 2) if c.arm.safety_mode == SAFETY_PROTECTIVE_STOP else 1,
    "runtime_state": lambda c, now: c.script.runtime_state(),
    "actual_digital_output_bits": lambda c, now: ((c.arm.digital_out & 0xFF) | ((c.arm.config_out & 0xFF) << 8)
                                                  | ((c.arm.tool_out & 0x3) << 16)),
    # standard and configurable outputs are wired back to the inputs of the same number
    "actual_digital_input_bits": lambda c, now: (c.arm.digital_out & 0xFF) | ((c.arm.config_out & 0xFF) << 8),
    **dict.fromkeys(("speed_scaling", "target_speed_fraction"), lambda c, now: c.arm.speed_slider),
    "joint_mode": lambda c, now: (253,) * 6,
    "joint_temperatures": lambda c, now: (30.0,) * 6,
    **dict.fromkeys(("actual_main_voltage", "actual_robot_voltage"), lambda c, now: 48.0),
}


def value(ctrl: Controller, name: str, now: float) -> Any:
    """The value of RTDE output variable ``name`` (zero for the ones not simulated)."""
    fn = _VALUES.get(name)
    if fn is not None:
        return fn(ctrl, now)
    prefix, _, index = name.rpartition("_")
    s = ctrl.script
    registers: dict[str, list[int] | list[float]] = {
        "output_int_register": s.out_int, "output_double_register": s.out_double,
        "input_int_register": s.in_int, "input_double_register": s.in_double}
    if prefix in registers:
        return registers[prefix][int(index)]
    fmt = _STRUCT[VARIABLE_TYPES[name]]
    n = int(fmt[:-1]) if len(fmt) > 1 else 1
    zero: Any = 0.0 if fmt[-1] == "d" else (False if fmt[-1] == "?" else 0)
    return zero if n == 1 else (zero,) * n


def _masked(old: int, values: dict[str, Any], name: str) -> int:
    mask = int(values[f"{name}_mask"])
    return (old & ~mask) | (int(values.get(name, 0)) & mask)


def apply_inputs(ctrl: Controller, values: dict[str, Any]) -> None:
    """Apply one RTDE input package: registers, digital outputs (masked), the speed slider; feed the watchdog."""
    s, arm = ctrl.script, ctrl.arm
    s.input_updated(list(values))
    for name, v in values.items():
        if name.startswith("input_int_register_"):
            s.in_int[int(name.rsplit("_", 1)[1])] = int(v)
        elif name.startswith("input_double_register_"):
            s.in_double[int(name.rsplit("_", 1)[1])] = float(v)
    if "standard_digital_output_mask" in values:
        arm.digital_out = _masked(arm.digital_out, values, "standard_digital_output")
    if "configurable_digital_output_mask" in values:
        arm.config_out = _masked(arm.config_out, values, "configurable_digital_output")
    if "tool_digital_output_mask" in values:
        arm.tool_out = _masked(arm.tool_out, values, "tool_digital_output")
    if int(values.get("speed_slider_mask", 0)) and "speed_slider_fraction" in values:
        arm.speed_slider = min(1.0, max(0.0, float(values["speed_slider_fraction"])))


class RtdeConnection:
    """One RTDE client: its recipes and, once started, its data stream."""

    def __init__(self, sock: socket.socket, ctrl: Controller, frequency_hz: float,
                 stopping: threading.Event) -> None:
        self.sock = sock
        self.ctrl = ctrl
        self.frequency_hz = frequency_hz
        self.stopping = stopping
        self.output_names: list[str] = []
        self.output_fmt = ""
        self.output_period_ticks = 1
        self.input_recipes: dict[int, tuple[list[str], str]] = {}
        self.started = False
        self.send_lock = threading.Lock()
        self.alive = True

    def send(self, kind: bytes, payload: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(struct.pack(">HB", len(payload) + 3, kind[0]) + payload)

    def _recv_exact(self, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("client closed")
            buf += chunk
        return bytes(buf)

    def serve(self) -> None:
        """Answer the client's packages until it or the emulator goes away."""
        try:
            while self.alive and not self.stopping.is_set():
                size, kind = struct.unpack(">HB", self._recv_exact(3))
                payload = self._recv_exact(size - 3) if size > 3 else b""
                self._handle(bytes([kind]), payload)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.alive = False
            with self.ctrl.lock:  # its input variables are free for another client
                for name in [n for n, owner in self.ctrl.input_owners.items() if owner is self]:
                    del self.ctrl.input_owners[name]
            with contextlib.suppress(OSError):
                self.sock.close()

    def _handle(self, kind: bytes, payload: bytes) -> None:
        if kind == b"V":
            self.send(b"V", b"\x01")
        elif kind == b"v":
            self.send(b"v", struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == b"O":
            self._setup_outputs(payload)
        elif kind == b"I":
            self._setup_inputs(payload)
        elif kind in (b"S", b"P"):
            self.started = kind == b"S"
            self.send(kind, b"\x01")
        elif kind == b"U":
            self._receive_inputs(payload)

    def _setup_outputs(self, payload: bytes) -> None:
        frequency = struct.unpack(">d", payload[:8])[0] if len(payload) >= 8 else 125.0
        names = [n for n in payload[8:].decode("ascii", "replace").split(",") if n]
        types = [VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
        self.output_names = names
        self.output_fmt = ">B" + "".join(_STRUCT[t] for t in types if t != "NOT_FOUND")
        hz = max(1.0, min(float(frequency), float(self.frequency_hz)))
        self.output_period_ticks = max(1, round(self.frequency_hz / hz))
        self.send(b"O", bytes([1]) + ",".join(types).encode())

    def _setup_inputs(self, payload: bytes) -> None:
        """An input recipe; a variable another live client has set up answers ``IN_USE`` (one writer each)."""
        names = [n for n in payload.decode("ascii", "replace").split(",") if n]
        recipe_id = len(self.input_recipes) + 1
        with self.ctrl.lock:
            owners = self.ctrl.input_owners
            types = ["IN_USE" if owners.get(n, self) is not self else VARIABLE_TYPES.get(n, "NOT_FOUND")
                     for n in names]
            refused = any(t in ("NOT_FOUND", "IN_USE") for t in types)
            if not refused:
                owners.update(dict.fromkeys(names, self))
        if "IN_USE" in types:
            log.warning("RTDE input recipe refused: %s in use by another client",
                        ", ".join(n for n, t in zip(names, types, strict=True) if t == "IN_USE"))
        if not refused:
            self.input_recipes[recipe_id] = (names, ">" + "".join(_STRUCT[t] for t in types))
        self.send(b"I", bytes([0 if refused else recipe_id]) + ",".join(types).encode())

    def _receive_inputs(self, payload: bytes) -> None:
        recipe = self.input_recipes.get(payload[0])
        if recipe is None:
            return
        names, fmt = recipe
        try:
            flat = struct.unpack(fmt, payload[1:1 + struct.calcsize(fmt)])
        except struct.error:
            log.warning("malformed RTDE input package for recipe %d", payload[0])
            return
        with self.ctrl.lock:
            apply_inputs(self.ctrl, dict(zip(names, flat, strict=True)))

    def pack_state(self, now: float) -> bytes:
        """One output data package (the caller holds the controller's lock)."""
        flat: list[Any] = [1]
        for name in self.output_names:
            if name not in VARIABLE_TYPES:
                continue
            v = value(self.ctrl, name, now)
            if isinstance(v, tuple):
                flat.extend(v)
            else:
                flat.append(v)
        return struct.pack(self.output_fmt, *flat)
