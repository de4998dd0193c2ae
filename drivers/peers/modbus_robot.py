"""A simple robot behind a Modbus TCP server (pymodbus), the peer of ``kind: modbus`` robots.

Many cells drive a robot through a PLC: the cell controller writes a target pose and a command
word, the PLC moves the robot and answers through a status word. This server plays that PLC and
its robot, with this register map (16-bit holding registers; float32 = two registers, word order
configurable, big-endian by default):

=========  ================================================================================
address    meaning
=========  ================================================================================
0-11       actual pose: x, y, z (mm), rx, ry, rz (deg, fixed-axis XYZ roll/pitch/yaw), float32
20-31      target pose, same form (written by the client)
32-33      speed, mm/s, float32 (written by the client)
40         command: 0 clear, 1 move linear, 2 stop (written by the client)
41         status: 0 ready, 1 busy, 2 done, 3 error
42         error code: 0 none, 1 target out of reach, 2 watchdog expired, 3 unknown command, 4 bad speed
50         client heartbeat: the client changes it at least every ``watchdog_s`` while a move runs
51         robot heartbeat: incremented 100 times a second while the robot controller runs
coils 0-7  digital outputs; discrete inputs 0-7: digital inputs (output *i* is wired to input *i*)
=========  ================================================================================

The handshake: write target and speed, write command 1; status goes 1 (busy) then 2 (done) or 3
(error, with the code); write command 0 and status returns to 0. Command 2 stops a move (status 2,
the robot stays where it stopped). The reachable workspace is a
1 m sphere around the base above z = 0.

Run it with ``python -m drivers.peers.modbus_robot --port 5020`` (or in-process: :class:`ModbusRobotSim`).
"""

from __future__ import annotations

import argparse
import math
import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from scipy.spatial.transform import Rotation, Slerp

from drivers import modbus_codec
from drivers.modbus_codec import WordOrder
from drivers.peers.modbus_serving import ServedModbus

ACTUAL_POSE = 0
TARGET_POSE = 20
SPEED = 32
COMMAND = 40
STATUS = 41
ERROR_CODE = 42
CLIENT_HEARTBEAT = 50
ROBOT_HEARTBEAT = 51
N_DIGITAL = 8

CMD_CLEAR, CMD_MOVE, CMD_STOP = 0, 1, 2
ST_READY, ST_BUSY, ST_DONE, ST_ERROR = 0, 1, 2, 3
ERR_NONE, ERR_REACH, ERR_WATCHDOG, ERR_COMMAND, ERR_SPEED = 0, 1, 2, 3, 4
REACH_MM = 1000.0
HOME_POSE = (400.0, 0.0, 300.0, 180.0, 0.0, 0.0)


def encode_float32(value: float, word_order: WordOrder) -> list[int]:
    return modbus_codec.encode(float(value), "float32", word_order)


def decode_float32(regs: list[int], word_order: WordOrder) -> float:
    return modbus_codec.decode(regs, "float32", word_order)


def _pose_to_T(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose[3:], degrees=True).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def _T_to_pose(T: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)])


@dataclass
class _Robot:
    """The robot and its PLC program; all times from ``time.monotonic``."""

    watchdog_s: float
    speed_override: float = 1.0
    """The controller's speed slider: moves run at this fraction of the commanded speed."""
    t0: float = field(default_factory=time.monotonic)
    T: NDArray[np.float64] = field(default_factory=lambda: _pose_to_T(np.array(HOME_POSE)))
    motion: tuple[float, float, NDArray[np.float64], NDArray[np.float64]] | None = None
    status: int = ST_READY
    error: int = ERR_NONE
    last_command: int = CMD_CLEAR
    client_heartbeat: int = 0
    heartbeat_changed: float = field(default_factory=time.monotonic)
    outputs: list[bool] = field(default_factory=lambda: [False] * N_DIGITAL)
    moves_completed: int = 0

    @staticmethod
    def _pose_at(motion: tuple[float, float, NDArray[np.float64], NDArray[np.float64]], t: float
                 ) -> NDArray[np.float64]:
        t_start, duration, T_a, T_b = motion
        s = 1.0 if duration <= 0 else min(1.0, max(0.0, (t - t_start) / duration))
        T = np.eye(4)
        T[:3, 3] = T_a[:3, 3] + s * (T_b[:3, 3] - T_a[:3, 3])
        rots = Rotation.from_matrix(np.stack([T_a[:3, :3], T_b[:3, :3]]))
        T[:3, :3] = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
        return T

    def step(self, now: float) -> None:
        if self.motion is None:
            return
        t_start, duration, _, T_b = self.motion
        deadline = self.heartbeat_changed + self.watchdog_s
        if now > deadline and deadline < t_start + duration:
            self.T = self._pose_at(self.motion, deadline)
            self.motion = None
            self.status, self.error = ST_ERROR, ERR_WATCHDOG
            return
        if now >= t_start + duration:
            self.T = T_b.copy()
            self.motion = None
            self.moves_completed += 1
            self.status = ST_DONE
        else:
            self.T = self._pose_at(self.motion, now)

    def command(self, value: int, target: NDArray[np.float64], speed_mm_s: float, now: float) -> None:
        if value == self.last_command:
            return
        self.last_command = value
        if value == CMD_CLEAR:
            if self.motion is None:
                self.status, self.error = ST_READY, ERR_NONE
            return
        if value == CMD_STOP:
            if self.motion is not None:
                self.T = self._pose_at(self.motion, now)
                self.motion = None
            self.status, self.error = ST_DONE, ERR_NONE
            return
        if value != CMD_MOVE:
            self.status, self.error = ST_ERROR, ERR_COMMAND
            return
        if self.status == ST_BUSY:
            return
        if not (math.isfinite(speed_mm_s) and 0 < speed_mm_s <= 2000):
            self.status, self.error = ST_ERROR, ERR_SPEED
            return
        if not np.all(np.isfinite(target)) or np.linalg.norm(target[:3]) > REACH_MM or target[2] < 0:
            self.status, self.error = ST_ERROR, ERR_REACH
            return
        T_b = _pose_to_T(target)
        duration = float(np.linalg.norm(T_b[:3, 3] - self.T[:3, 3])) / (speed_mm_s * self.speed_override)
        self.heartbeat_changed = now
        self.motion = (now, duration, self.T.copy(), T_b)
        self.status, self.error = ST_BUSY, ERR_NONE


class ModbusRobotSim:
    """The Modbus TCP server and its robot; ``start()`` runs it in a background thread."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 5020,
        device_id: int = 1,
        word_order: WordOrder = "big",
        watchdog_s: float = 1.0,
        speed_override: float = 1.0,
    ) -> None:
        self.host, self.port, self.device_id, self.word_order = host, port, device_id, word_order
        self.robot = _Robot(watchdog_s=watchdog_s, speed_override=speed_override)
        self._lock = threading.Lock()
        self._hr: list[int] = [0] * 64  # the client-visible copy of what the client wrote
        self._serving = ServedModbus("modbus-robot-sim")

    def _device(self) -> SimDevice:
        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        return SimDevice(
            id=self.device_id,
            simdata=(
                bits,
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(0, count=64, values=0, datatype=DataType.REGISTERS)],
                [SimData(0, count=4, values=0, datatype=DataType.REGISTERS)],
            ),
            action=self._action,
        )

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> None:
        now = time.monotonic()
        with self._lock:
            r = self.robot
            if function_code in (5, 15) and set_values is not None:  # coils
                for i, v in enumerate(set_values):
                    if 0 <= address + i < N_DIGITAL:
                        r.outputs[address + i] = bool(v)
            if function_code == 2:  # discrete inputs: wired from the outputs
                word = sum(1 << i for i, on in enumerate(r.outputs) if on)
                current_registers[0 - start_address] = word
            if function_code in (3, 6, 16, 23):
                if set_values is not None:
                    for i, v in enumerate(set_values):
                        if 0 <= address + i < len(self._hr):
                            self._hr[address + i] = int(v)
                    written = range(address, address + len(set_values))
                    if CLIENT_HEARTBEAT in written and self._hr[CLIENT_HEARTBEAT] != r.client_heartbeat:
                        r.client_heartbeat = self._hr[CLIENT_HEARTBEAT]
                        r.heartbeat_changed = now
                    r.step(now)
                    if COMMAND in written:
                        target = np.array(
                            [
                                decode_float32(self._hr[TARGET_POSE + 2 * k : TARGET_POSE + 2 * k + 2], self.word_order)
                                for k in range(6)
                            ]
                        )
                        speed = decode_float32(self._hr[SPEED : SPEED + 2], self.word_order)
                        r.command(self._hr[COMMAND], target, speed, now)
                else:
                    r.step(now)
                self._publish(current_registers, start_address, now)
        return None

    def _publish(self, regs: list[int], start: int, now: float) -> None:
        r = self.robot
        pose = _T_to_pose(r.T)
        for k in range(6):
            regs[ACTUAL_POSE + 2 * k - start : ACTUAL_POSE + 2 * k + 2 - start] = encode_float32(
                pose[k], self.word_order
            )
        regs[STATUS - start] = r.status
        regs[ERROR_CODE - start] = r.error
        regs[ROBOT_HEARTBEAT - start] = int((now - r.t0) * 100) & 0xFFFF

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> ModbusRobotSim:
        self._serving.start(
            lambda: ModbusTcpServer(self._device(), address=(self.host, self.port)),
            f"Modbus robot simulator cannot listen on {self.host}:{self.port}")
        return self

    def stop(self) -> None:
        self._serving.stop()


def run(
    host: str = "127.0.0.1",
    port: int = 5020,
    device_id: int = 1,
    word_order: WordOrder = "big",
    watchdog_s: float = 1.0,
    speed_override: float = 1.0,
) -> None:
    """Serve until SIGINT or SIGTERM."""
    sim = ModbusRobotSim(host, port, device_id, word_order, watchdog_s, speed_override).start()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    print(f"Modbus robot simulator ready on {host}:{port} (device id {device_id}, {word_order} word order)", flush=True)
    while not done.wait(0.5):
        pass
    sim.stop()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="A simple robot behind a Modbus TCP server (see the register map)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=5020)
    p.add_argument("--device-id", type=int, default=1)
    p.add_argument("--word-order", choices=("big", "little"), default="big")
    p.add_argument("--watchdog-s", type=float, default=1.0)
    p.add_argument("--speed-override", type=float, default=1.0,
                   help="fraction of the commanded speed the robot really moves at (the speed slider, 0-1]")
    a = p.parse_args(argv)
    if not 0 < a.speed_override <= 1:
        p.error("--speed-override must be in (0, 1]")
    run(a.host, a.port, a.device_id, a.word_order, a.watchdog_s, a.speed_override)


if __name__ == "__main__":
    main()
