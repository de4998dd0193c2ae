"""A Universal Robots controller emulator that the real ``ur_rtde`` clients connect to.

It speaks the controller's side of three protocols on one host:

- **RTDE** (port 30004): protocol version ``V``, controller version ``v``, output/input recipe
  setup ``O``/``I``, start ``S``, pause ``P`` and data packages ``U``; big-endian; published at
  up to 500 Hz (an e-Series controller, version 5.11).
- **Dashboard server** (port 29999): the line protocol (``robotmode``, ``power on``,
  ``brake release``, ``unlock protective stop``, ``PolyscopeVersion``, ...).
- **Script server** (port 30003, also 30001/30002): receives URScript. When ``ur_rtde``'s control
  script arrives, the emulator plays that script's part of the register handshake: program
  running (robot status bits 0b11, runtime state 2) and output int register 0 = 1 (ready); a
  command in input int register 0 runs, output int register 0 = 2 when it is done, back to 1 when
  the client clears the command; 255 stops the script.

The simulated arm is a UR5e (its published DH parameters): ``moveL`` moves the TCP in a straight
line at the commanded speed (m/s), ``moveJ`` moves the joints at the commanded speed (rad/s),
``stopL``/``stopJ`` stop, a protective stop (``triggerProtectiveStop``) halts it until the
dashboard's ``unlock protective stop``. Standard digital outputs are wired back to the standard
digital inputs (output *i* drives input *i*), so IO can be tested through the real protocol.

We write our own here because no UR simulator runs without Docker (URSim); the protocol details
follow ``ur_rtde``'s sources (``rtde.cpp``, ``rtde_control_interface.cpp``, ``dashboard_client.cpp``).
``ur_rtde`` holds the GIL during its calls, so run the emulator in its own process
(:func:`run`, or ``cellctl sim ur``, or ``python -m drivers.sim.ur_emulator``).

``ur_rtde`` always connects to the fixed ports (30004, 29999, 30003); callers that start
emulators in tests serialise on :func:`fixed_port_lock`.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import logging
import math
import signal
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

log = logging.getLogger("cellctl.ur_emulator")

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
CONTROLLER_VERSION = (5, 11, 1, 108318)
POLYSCOPE_VERSION = "URSoftware 5.11.1.108318 (Nov 29 2021)"
SERIAL_NUMBER = "20235500001"
PORT_LOCK_PATH = "/tmp/cellctl-ur-emulator-ports.lock"
"""File lock held by whoever runs an emulator on 127.0.0.1's fixed UR ports in tests/benchmarks."""

# robot modes (RTDE robot_mode) and safety modes
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL = 1
SAFETY_PROTECTIVE_STOP = 3
ROBOT_MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
                    3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING"}

# control-script command codes (ur_rtde's RobotCommand::Type)
CMD_NO_CMD = 0
CMD_MOVEJ = 1
CMD_MOVEL = 3
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_FK_DEFAULT = 43
CMD_FK_ARGS = 44
CMD_STOP_SCRIPT = 255
CONTINUOUS_CMDS = {9, 10, 11, 12, 24, 6, 99, 38, 25, 26, 27, 55}
"""Commands the client does not wait for (servo/speed/force/watchdog...): acknowledged, ignored."""

# UR5e DH parameters (Universal Robots' published values)
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
HOME_Q = (0.0, -1.9, 1.9, -1.5708, -1.5708, 0.0)


def forward_kinematics(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """UR5e flange pose ``T_base_tool`` (4x4, metres) for joint angles ``q`` (radians)."""
    T = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct],
                          [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    return T


def _pose_to_T(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:6]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def _T_to_pose(T: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def inverse_kinematics(T_target: NDArray[np.float64],
                       q_near: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Joint angles near ``q_near`` that reach ``T_target``, or None when it is out of reach."""
    R_target = Rotation.from_matrix(T_target[:3, :3])

    def residual(q: NDArray[np.float64]) -> NDArray[np.float64]:
        T = forward_kinematics(q)
        rot_err = (R_target.inv() * Rotation.from_matrix(T[:3, :3])).as_rotvec()
        return np.concatenate([T[:3, 3] - T_target[:3, 3], 0.2 * rot_err])

    sol = least_squares(residual, np.asarray(q_near, dtype=np.float64), method="lm", xtol=1e-12, ftol=1e-12)
    if not sol.success or np.max(np.abs(residual(sol.x))) > 1e-6:
        return None
    q: NDArray[np.float64] = sol.x
    return q


# -- RTDE variable types --------------------------------------------------------------------------

_STRUCT = {"DOUBLE": "d", "UINT64": "Q", "UINT32": "I", "INT32": "i", "UINT8": "B", "BOOL": "?",
           "VECTOR6D": "6d", "VECTOR3D": "3d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}

_VARIABLE_TYPES: dict[str, str] = {
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
    _VARIABLE_TYPES[f"output_int_register_{_i}"] = "INT32"
    _VARIABLE_TYPES[f"input_int_register_{_i}"] = "INT32"
    _VARIABLE_TYPES[f"output_double_register_{_i}"] = "DOUBLE"
    _VARIABLE_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    _VARIABLE_TYPES[f"input_bit_register_{_i}"] = "BOOL"
    _VARIABLE_TYPES[f"output_bit_register_{_i}"] = "BOOL"


@dataclass
class _Motion:
    kind: str  # "linear" or "joint"
    t0: float
    duration_s: float
    q_start: NDArray[np.float64]
    q_end: NDArray[np.float64]
    T_start: NDArray[np.float64]
    T_end: NDArray[np.float64]
    waiting_client: bool  # a synchronous command: signal done when finished


@dataclass
class _RobotSim:
    """The simulated controller state. Every access is under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    t_start: float = field(default_factory=time.monotonic)
    q: NDArray[np.float64] = field(default_factory=lambda: np.array(HOME_Q, dtype=np.float64))
    robot_mode: int = ROBOT_MODE_RUNNING
    safety_mode: int = SAFETY_NORMAL
    program_running: bool = False
    script_receiving_since: float | None = None
    motion: _Motion | None = None
    digital_out: int = 0
    config_out: int = 0
    tool_out: int = 0
    speed_slider: float = 1.0
    in_int: list[int] = field(default_factory=lambda: [0] * 48)
    in_double: list[float] = field(default_factory=lambda: [0.0] * 48)
    out_int: list[int] = field(default_factory=lambda: [0] * 48)
    out_double: list[float] = field(default_factory=lambda: [0.0] * 48)
    cmd_state: str = "ready"  # ready | busy | done
    moves_completed: int = 0
    last_move: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.T = forward_kinematics(self.q)
        self.T_cmd = self.T.copy()

    # -- derived values ------------------------------------------------------------------------
    def robot_status_bits(self) -> int:
        powered = self.robot_mode in (4, 5, 6, 7)
        return (1 if powered else 0) | (2 if self.program_running else 0)

    def safety_status_bits(self) -> int:
        return (1 << 2) if self.safety_mode == SAFETY_PROTECTIVE_STOP else 1

    def runtime_state(self) -> int:
        return 2 if self.program_running else 1

    def value(self, name: str, now: float) -> Any:
        if name == "timestamp":
            return now - self.t_start
        if name in ("actual_q", "target_q"):
            return tuple(self.q)
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return tuple(_T_to_pose(self.T))
        if name in ("actual_TCP_speed", "target_TCP_speed"):
            return self._tcp_speed(now)
        if name in ("actual_qd", "target_qd"):
            m = self.motion
            if m is None or m.duration_s <= 0:
                return (0.0,) * 6
            return tuple(float(v) for v in (m.q_end - m.q_start) / m.duration_s)
        if name == "robot_mode":
            return self.robot_mode
        if name in ("safety_mode", "safety_status"):
            return self.safety_mode
        if name == "robot_status_bits":
            return self.robot_status_bits()
        if name == "safety_status_bits":
            return self.safety_status_bits()
        if name == "runtime_state":
            return self.runtime_state()
        if name == "actual_digital_output_bits":
            return (self.digital_out & 0xFF) | ((self.config_out & 0xFF) << 8) | ((self.tool_out & 0x3) << 16)
        if name == "actual_digital_input_bits":
            return (self.digital_out & 0xFF) | ((self.config_out & 0xFF) << 8)
        if name in ("speed_scaling", "target_speed_fraction"):
            return self.speed_slider
        if name == "joint_mode":
            return (253,) * 6
        if name == "joint_temperatures":
            return (30.0,) * 6
        if name in ("actual_main_voltage", "actual_robot_voltage"):
            return 48.0
        if name.startswith("output_int_register_"):
            return self.out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self.out_double[int(name.rsplit("_", 1)[1])]
        if name.startswith("input_int_register_"):
            return self.in_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("input_double_register_"):
            return self.in_double[int(name.rsplit("_", 1)[1])]
        type_name = _VARIABLE_TYPES[name]
        fmt = _STRUCT[type_name]
        n = int(fmt[:-1]) if len(fmt) > 1 else 1
        zero: Any = 0.0 if fmt[-1] == "d" else (False if fmt[-1] == "?" else 0)
        return zero if n == 1 else (zero,) * n

    def _tcp_speed(self, now: float) -> tuple[float, ...]:
        m = self.motion
        if m is None or m.duration_s <= 0:
            return (0.0,) * 6
        v = (m.T_end[:3, 3] - m.T_start[:3, 3]) / m.duration_s
        return (float(v[0]), float(v[1]), float(v[2]), 0.0, 0.0, 0.0)

    # -- input ------------------------------------------------------------------------------------
    def apply_inputs(self, values: dict[str, Any]) -> None:
        for name, v in values.items():
            if name.startswith("input_int_register_"):
                self.in_int[int(name.rsplit("_", 1)[1])] = int(v)
            elif name.startswith("input_double_register_"):
                self.in_double[int(name.rsplit("_", 1)[1])] = float(v)
        if "standard_digital_output_mask" in values:
            mask = int(values["standard_digital_output_mask"])
            val = int(values.get("standard_digital_output", 0))
            self.digital_out = (self.digital_out & ~mask) | (val & mask)
        if "configurable_digital_output_mask" in values:
            mask = int(values["configurable_digital_output_mask"])
            val = int(values.get("configurable_digital_output", 0))
            self.config_out = (self.config_out & ~mask) | (val & mask)
        if "tool_digital_output_mask" in values:
            mask = int(values["tool_digital_output_mask"])
            val = int(values.get("tool_digital_output", 0))
            self.tool_out = (self.tool_out & ~mask) | (val & mask)
        if int(values.get("speed_slider_mask", 0)) and "speed_slider_fraction" in values:
            self.speed_slider = min(1.0, max(0.0, float(values["speed_slider_fraction"])))

    # -- the 500 Hz step: motion and the control script's command handshake --------------------
    def step(self, now: float) -> None:
        self._step_motion(now)
        if self.script_receiving_since is not None and now - self.script_receiving_since > 0.15:
            self.script_receiving_since = None
            if self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_NORMAL:
                self.program_running = True
                self.cmd_state = "ready"
                self.out_int[0] = 1
                log.info("control script running")
            else:
                log.warning("control script rejected: robot is not running (mode %s, safety %s)",
                            ROBOT_MODE_NAMES.get(self.robot_mode), self.safety_mode)
        if not self.program_running:
            return
        cmd = self.in_int[0]
        if self.cmd_state == "ready" and cmd != CMD_NO_CMD:
            self._start_command(cmd, now)
        elif self.cmd_state == "done" and cmd == CMD_NO_CMD:
            self.cmd_state = "ready"
            self.out_int[0] = 1

    def _finish_command(self) -> None:
        self.cmd_state = "done"
        self.out_int[0] = 2

    def stop_program(self, reason: str) -> None:
        if self.program_running:
            log.info("control script stopped: %s", reason)
        self.program_running = False
        self.motion = None
        self.out_int[0] = 0
        self.cmd_state = "ready"

    def _start_command(self, cmd: int, now: float) -> None:
        d = self.in_double
        asynchronous = self.in_int[1] == 1
        if cmd == CMD_STOP_SCRIPT:
            self.stop_program("stopScript")
            return
        if cmd in CONTINUOUS_CMDS:
            return  # servo/speed/watchdog streams: the client does not wait for "done"; not simulated
        if cmd in (CMD_MOVEL, CMD_MOVEJ):
            self.cmd_state = "busy"
            if cmd == CMD_MOVEL:
                ok = self._start_linear(np.array(d[0:6]), speed_m_s=d[6], now=now, waiting=not asynchronous)
            else:
                ok = self._start_joint(np.array(d[0:6]), speed_rad_s=d[6], now=now, waiting=not asynchronous)
            if not ok:
                self.stop_program("inverse kinematics failed or target unreachable")
                return
            if asynchronous:
                self._finish_command()
            return
        if cmd in (CMD_STOPL, CMD_STOPJ):
            self._halt()
        elif cmd == CMD_PROTECTIVE_STOP:
            self._halt()
            self.safety_mode = SAFETY_PROTECTIVE_STOP
        elif cmd == CMD_FK_DEFAULT:
            self.out_double[0:6] = list(_T_to_pose(self.T))
        elif cmd == CMD_FK_ARGS:
            self.out_double[0:6] = list(_T_to_pose(forward_kinematics(np.array(d[0:6]))))
        self._finish_command()

    def _halt(self) -> None:
        if self.motion is not None and self.motion.waiting_client:
            pass  # the waiting command gets no "done": the client sees the stop through its own stop call
        self.motion = None

    def _start_linear(self, pose: NDArray[np.float64], speed_m_s: float, now: float, waiting: bool) -> bool:
        if not (np.all(np.isfinite(pose)) and math.isfinite(speed_m_s) and speed_m_s > 0):
            return False
        T_end = _pose_to_T(pose)
        q_end = inverse_kinematics(T_end, self.q)
        if q_end is None:
            return False
        dist = float(np.linalg.norm(T_end[:3, 3] - self.T[:3, 3]))
        angle = float(np.linalg.norm((Rotation.from_matrix(self.T[:3, :3]).inv()
                                      * Rotation.from_matrix(T_end[:3, :3])).as_rotvec()))
        duration = max(dist / (speed_m_s * self.speed_slider), angle / 1.0, 0.0)
        self.motion = _Motion("linear", now, duration, self.q.copy(), q_end, self.T.copy(), T_end, waiting)
        self.last_move = {"kind": "moveL", "pose": pose.tolist(), "speed": speed_m_s}
        return True

    def _start_joint(self, q_end: NDArray[np.float64], speed_rad_s: float, now: float, waiting: bool) -> bool:
        if not (np.all(np.isfinite(q_end)) and math.isfinite(speed_rad_s) and speed_rad_s > 0):
            return False
        duration = float(np.max(np.abs(q_end - self.q))) / (speed_rad_s * self.speed_slider)
        T_end = forward_kinematics(q_end)
        self.motion = _Motion("joint", now, duration, self.q.copy(), q_end.copy(), self.T.copy(), T_end,
                              waiting)
        self.last_move = {"kind": "moveJ", "q": q_end.tolist(), "speed": speed_rad_s}
        return True

    def _step_motion(self, now: float) -> None:
        m = self.motion
        if m is None:
            return
        s = 1.0 if m.duration_s <= 0 else min(1.0, (now - m.t0) / m.duration_s)
        self.q = m.q_start + s * (m.q_end - m.q_start)
        if m.kind == "linear":
            T = np.eye(4)
            T[:3, 3] = m.T_start[:3, 3] + s * (m.T_end[:3, 3] - m.T_start[:3, 3])
            rots = Rotation.from_matrix(np.stack([m.T_start[:3, :3], m.T_end[:3, :3]]))
            T[:3, :3] = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
            self.T = T
        else:
            self.T = forward_kinematics(self.q)
        if s >= 1.0:
            self.T = m.T_end.copy()
            self.q = m.q_end.copy()
            self.motion = None
            self.moves_completed += 1
            if m.waiting_client and self.cmd_state == "busy":
                self._finish_command()


# -- RTDE server ------------------------------------------------------------------------------------


class _RtdeConnection:
    """One RTDE client: its recipes and, once started, its data stream."""

    def __init__(self, sock: socket.socket, emulator: UrEmulator) -> None:
        self.sock = sock
        self.emu = emulator
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
        try:
            while self.alive and not self.emu.stopping.is_set():
                size, kind = struct.unpack(">HB", self._recv_exact(3))
                payload = self._recv_exact(size - 3) if size > 3 else b""
                self._handle(bytes([kind]), payload)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.alive = False
            self.emu.drop_rtde(self)
            with contextlib.suppress(OSError):
                self.sock.close()

    def _handle(self, kind: bytes, payload: bytes) -> None:
        if kind == b"V":
            self.send(b"V", b"\x01")
        elif kind == b"v":
            self.send(b"v", struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == b"O":
            frequency = struct.unpack(">d", payload[:8])[0] if len(payload) >= 8 else 125.0
            names = [n for n in payload[8:].decode("ascii", "replace").split(",") if n]
            types = [_VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
            self.output_names = names
            self.output_fmt = ">B" + "".join(_STRUCT[t] for t in types if t != "NOT_FOUND")
            hz = max(1.0, min(float(frequency), float(self.emu.frequency_hz)))
            self.output_period_ticks = max(1, round(self.emu.frequency_hz / hz))
            self.send(b"O", bytes([1]) + ",".join(types).encode())
        elif kind == b"I":
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            types = [_VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
            recipe_id = len(self.input_recipes) + 1
            in_use = any(t == "NOT_FOUND" for t in types)
            if not in_use:
                self.input_recipes[recipe_id] = (names, ">" + "".join(_STRUCT[t] for t in types))
            self.send(b"I", bytes([0 if in_use else recipe_id]) + ",".join(types).encode())
        elif kind == b"S":
            self.started = True
            self.send(b"S", b"\x01")
        elif kind == b"P":
            self.started = False
            self.send(b"P", b"\x01")
        elif kind == b"U":
            recipe_id = payload[0]
            recipe = self.input_recipes.get(recipe_id)
            if recipe is None:
                return
            names, fmt = recipe
            try:
                flat = struct.unpack(fmt, payload[1:1 + struct.calcsize(fmt)])
            except struct.error:
                log.warning("malformed RTDE input package for recipe %d", recipe_id)
                return
            self.emu.apply_inputs(dict(zip(names, flat, strict=True)))

    def pack_state(self, sim: _RobotSim, now: float) -> bytes:
        flat: list[Any] = [1]
        for name in self.output_names:
            if name not in _VARIABLE_TYPES:
                continue
            v = sim.value(name, now)
            if isinstance(v, tuple):
                flat.extend(v)
            else:
                flat.append(v)
        return struct.pack(self.output_fmt, *flat)


class UrEmulator:
    """The emulator: servers on the three UR ports and the 500 Hz controller loop."""

    def __init__(self, host: str = "127.0.0.1", rtde_port: int = RTDE_PORT,
                 dashboard_port: int = DASHBOARD_PORT, script_ports: tuple[int, ...] = SCRIPT_PORTS,
                 frequency_hz: float = 500.0) -> None:
        self.host = host
        self.ports = {"rtde": rtde_port, "dashboard": dashboard_port}
        self.script_ports = script_ports
        self.frequency_hz = frequency_hz
        self.sim = _RobotSim()
        self.stopping = threading.Event()
        self._servers: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._rtde_clients: list[_RtdeConnection] = []
        self._clients_lock = threading.Lock()
        self._client_socks: list[socket.socket] = []

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Bind every port (raises OSError naming the port when one is taken) and start serving."""
        specs: list[tuple[int, Any]] = [(self.ports["rtde"], self._serve_rtde),
                                        (self.ports["dashboard"], self._serve_dashboard)]
        specs += [(p, self._serve_script) for p in self.script_ports]
        for port, handler in specs:
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                srv.bind((self.host, port))
            except OSError as exc:
                srv.close()
                self.stop()
                raise OSError(exc.errno, f"UR emulator: cannot listen on {self.host}:{port}: {exc.strerror}; "
                                         "is another emulator or a robot service using it?") from exc
            srv.listen(8)
            srv.settimeout(0.2)
            self._servers.append(srv)
            self._spawn(self._accept_loop, srv, handler)
        self._spawn(self._control_loop)
        log.info("UR emulator listening on %s (RTDE %d, dashboard %d, script %s)", self.host,
                 self.ports["rtde"], self.ports["dashboard"], ",".join(map(str, self.script_ports)))

    def stop(self) -> None:
        self.stopping.set()
        for s in self._servers + self._client_socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._servers.clear()

    def _spawn(self, target: Any, *args: Any) -> None:
        t = threading.Thread(target=target, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept_loop(self, srv: socket.socket, handler: Any) -> None:
        while not self.stopping.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._clients_lock:
                self._client_socks.append(conn)
            threading.Thread(target=handler, args=(conn,), daemon=True).start()

    # -- RTDE --------------------------------------------------------------------------------------
    def _serve_rtde(self, conn: socket.socket) -> None:
        client = _RtdeConnection(conn, self)
        with self._clients_lock:
            self._rtde_clients.append(client)
        client.serve()

    def drop_rtde(self, client: _RtdeConnection) -> None:
        with self._clients_lock:
            if client in self._rtde_clients:
                self._rtde_clients.remove(client)

    def apply_inputs(self, values: dict[str, Any]) -> None:
        with self.sim.lock:
            self.sim.apply_inputs(values)

    def _control_loop(self) -> None:
        period = 1.0 / self.frequency_hz
        tick = 0
        next_t = time.monotonic()
        while not self.stopping.is_set():
            now = time.monotonic()
            with self._clients_lock:
                clients = [c for c in self._rtde_clients if c.started and c.alive]
            packets: list[tuple[_RtdeConnection, bytes]] = []
            with self.sim.lock:
                self.sim.step(now)
                for c in clients:
                    if tick % c.output_period_ticks == 0:
                        packets.append((c, c.pack_state(self.sim, now)))
            for c, payload in packets:
                try:
                    c.send(b"U", payload)
                except OSError:
                    c.alive = False
                    with contextlib.suppress(OSError):
                        c.sock.shutdown(socket.SHUT_RDWR)
            tick += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                next_t = time.monotonic()  # fell behind (machine busy): do not burst

    # -- script server -----------------------------------------------------------------------------
    def _serve_script(self, conn: socket.socket) -> None:
        conn.settimeout(0.5)
        received = 0
        with contextlib.suppress(OSError):
            while not self.stopping.is_set():
                try:
                    chunk = conn.recv(65536)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                received += len(chunk)
                with self.sim.lock:
                    if self.sim.program_running:
                        self.sim.stop_program("a new script replaces the running one")
                    self.sim.script_receiving_since = time.monotonic()
        log.debug("script connection closed after %d bytes", received)
        with contextlib.suppress(OSError):
            conn.close()

    # -- dashboard ---------------------------------------------------------------------------------
    def _serve_dashboard(self, conn: socket.socket) -> None:
        with contextlib.suppress(OSError):
            conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while not self.stopping.is_set():
                chunk = conn.recv(4096)
                if not chunk:
                    break
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    reply, close = self.dashboard_reply(line.decode("utf-8", "replace").strip())
                    conn.sendall(reply.encode() + b"\n")
                    if close:
                        return
        with contextlib.suppress(OSError):
            conn.close()

    def dashboard_reply(self, command: str) -> tuple[str, bool]:
        """The dashboard server's answer to one command line, and whether it closes the connection."""
        c = command.lower()
        s = self.sim
        with s.lock:
            if c == "polyscopeversion":
                return POLYSCOPE_VERSION, False
            if c == "get serial number":
                return SERIAL_NUMBER, False
            if c == "get robot model":
                return "UR5", False
            if c == "robotmode":
                return f"Robotmode: {ROBOT_MODE_NAMES.get(s.robot_mode, 'UNKNOWN')}", False
            if c in ("safetymode", "safetystatus"):
                name = "PROTECTIVE_STOP" if s.safety_mode == SAFETY_PROTECTIVE_STOP else "NORMAL"
                return f"{'Safetymode' if c == 'safetymode' else 'Safetystatus'}: {name}", False
            if c == "running":
                return f"Program running: {'true' if s.program_running else 'false'}", False
            if c == "programstate":
                return ("PLAYING rtde_control" if s.program_running else "STOPPED <unnamed>"), False
            if c == "is in remote control":
                return "true", False
            if c == "power on":
                if s.robot_mode == ROBOT_MODE_POWER_OFF:
                    s.robot_mode = ROBOT_MODE_IDLE
                return "Powering on", False
            if c == "power off":
                s.robot_mode = ROBOT_MODE_POWER_OFF
                s.stop_program("power off")
                return "Powering off", False
            if c == "brake release":
                if s.robot_mode in (ROBOT_MODE_IDLE, 4):
                    s.robot_mode = ROBOT_MODE_RUNNING
                return "Brake releasing", False
            if c == "unlock protective stop":
                if s.safety_mode != SAFETY_PROTECTIVE_STOP:
                    return ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause "
                            "of protective stop before unlocking"), False
                s.safety_mode = SAFETY_NORMAL
                return "Protective stop releasing", False
            if c == "stop":
                s.stop_program("dashboard stop")
                return "Stopped", False
            if c == "play":
                return "Failed to execute: play", False
            if c == "pause":
                return "Failed to execute: pause", False
            if c == "close popup":
                return "closing popup", False
            if c == "close safety popup":
                return "closing safety popup", False
            if c == "restart safety":
                return "Restarting safety", False
            if c == "get loaded program":
                return "No program loaded", False
            if c == "isprogramsaved":
                return "true <unnamed>", False
            if c.startswith("popup "):
                return "showing popup", False
            if c.startswith("addtolog "):
                return "Added log message", False
            if c.startswith("setuserrole "):
                return "Setting user role: " + command.split(" ", 1)[1], False
            if c.startswith("load "):
                return "File not found: " + command.split(" ", 1)[1], False
            if c == "quit":
                return "Disconnected", True
            if c == "shutdown":
                return "Shutting down", True
            return f"could not understand: '{command}'", False


@contextlib.contextmanager
def fixed_port_lock(timeout_s: float = 120.0) -> Iterator[None]:
    """Hold the lock for 127.0.0.1's fixed UR ports (``ur_rtde`` cannot use other ports)."""
    with open(PORT_LOCK_PATH, "a+") as fh:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"UR emulator ports are held by another process for {timeout_s} s "
                                       f"(lock file {PORT_LOCK_PATH})") from None
                time.sleep(0.1)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def run(host: str = "127.0.0.1", rtde_port: int = RTDE_PORT, dashboard_port: int = DASHBOARD_PORT,
        script_ports: tuple[int, ...] = SCRIPT_PORTS, frequency_hz: float = 500.0) -> None:
    """Run the emulator until SIGINT or SIGTERM (the entry point of ``cellctl sim ur``)."""
    emulator = UrEmulator(host, rtde_port, dashboard_port, script_ports, frequency_hz)
    done = threading.Event()

    def _on_signal(signum: int, frame: Any) -> None:
        done.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        emulator.start()
        print(f"UR emulator ready on {host} (RTDE {rtde_port}, dashboard {dashboard_port})", flush=True)
        while not done.wait(0.5):
            pass
    finally:
        emulator.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="Universal Robots RTDE/dashboard emulator for ur_rtde clients")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--frequency-hz", type=float, default=500.0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    run(host=args.host, frequency_hz=args.frequency_hz)


if __name__ == "__main__":
    main()
