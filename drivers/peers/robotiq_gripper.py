"""A simulated Robotiq-style 2-finger gripper on Modbus RTU, the peer of ``kind: robotiq_gripper``.

It follows Robotiq's 2F register map (device id 9, 115200 baud by default):

- holding registers 1000-1002 (written by the robot, FC16): byte 0 action request (rACT bit 0
  activate, rGTO bit 3 go to position, rATR bit 4 automatic release), bytes 1-2 reserved, byte 3
  position request (0 open .. 255 closed), byte 4 speed, byte 5 force;
- input registers 2000-2002 (read by the robot, FC04): byte 0 gripper status (gACT bit 0, gGTO
  bit 3, gSTA bits 4-5: 0 reset, 1 activating, 3 active; gOBJ bits 6-7: 0 moving, 1 contact while
  opening, 2 contact while closing, 3 at the requested position), byte 1 reserved, byte 2 fault
  (0x05 action before activation completed, 0x07 action without the activation bit), byte 3
  position request echo, byte 4 position, byte 5 motor current (~ force while gripping).

Activation takes ``activation_s``; the fingers move at 100 + 1.5 x speed position units per second;
an object sits at position ``--object-at`` (closing past it stops there with gOBJ = 2; -1 = none).

Run it on one end of a pty pair: ``python -m drivers.peers.robotiq_gripper --port /tmp/gripper-b``.
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from dataclasses import dataclass, field

from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.peers.modbus_serving import ServedModbus

OUT_BASE = 1000
IN_BASE = 2000


@dataclass
class GripperModel:
    """The gripper's mechanics and its status bytes (times from ``time.monotonic``)."""

    object_at: int = 200
    activation_s: float = 0.3
    act: bool = False
    gto: bool = False
    activated_at: float | None = None
    position: float = 0.0
    request: int = 0
    speed: int = 255
    force: int = 128
    fault: int = 0
    t_last: float = field(default_factory=time.monotonic)
    blocked: bool = False

    def active(self, now: float) -> bool:
        return self.act and self.activated_at is not None and now - self.activated_at >= self.activation_s

    def step(self, now: float) -> None:
        dt, self.t_last = now - self.t_last, now
        if not (self.active(now) and self.gto):
            return
        rate = 100.0 + 1.5 * self.speed
        target = float(self.request)
        if self.object_at >= 0 and target > self.position and self.position <= self.object_at < target:
            target = float(self.object_at)
        if abs(target - self.position) <= rate * dt:
            self.position = target
        else:
            self.position += rate * dt if target > self.position else -rate * dt
        self.blocked = self.position == target and target != float(self.request)

    def write(self, regs: list[int], now: float) -> None:
        self.step(now)
        action = regs[0] >> 8
        act, gto = bool(action & 0x01), bool(action & 0x08)
        if act and not self.act:
            self.activated_at = now
            self.fault = 0
        if not act:
            self.activated_at = None
            self.gto = False
        self.act = act
        self.request, self.speed, self.force = regs[1] & 0xFF, regs[2] >> 8, regs[2] & 0xFF
        if gto and not self.act:
            self.fault, self.gto = 0x07, False
        elif gto and not self.active(now):
            self.fault, self.gto = 0x05, False
        else:
            self.gto = gto
            if gto:
                self.fault = 0
                self.blocked = False

    def inputs(self, now: float) -> list[int]:
        self.step(now)
        sta = 0 if not self.act else (3 if self.active(now) else 1)
        pos = int(round(self.position))
        if not self.gto or not self.active(now) or pos != self.request and not self.blocked:
            obj = 0
        elif self.blocked:
            obj = 2 if self.request > pos else 1
        else:
            obj = 3
        status = int(self.act) | (int(self.gto) << 3) | (sta << 4) | (obj << 6)
        current = (self.force // 2) if obj in (1, 2) else (10 if obj == 0 and self.gto else 0)
        return [status << 8, (self.fault << 8) | self.request, (pos << 8) | current]


class GripperSim:
    """The Modbus RTU server of the gripper on a serial port; ``start()`` runs it in a thread."""

    def __init__(self, port: str, device_id: int = 9, baudrate: int = 115200, object_at: int = 200) -> None:
        self.port, self.device_id, self.baudrate = port, device_id, baudrate
        self.model = GripperModel(object_at=object_at)
        self._lock = threading.Lock()
        self._serving = ServedModbus("gripper-sim")

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
            if function_code in (6, 16) and set_values is not None and OUT_BASE <= address < OUT_BASE + 3:
                regs = list(current_registers[OUT_BASE - start_address : OUT_BASE - start_address + 3])
                for i, v in enumerate(set_values):
                    if 0 <= address + i - OUT_BASE < 3:
                        regs[address + i - OUT_BASE] = int(v)
                self.model.write(regs, now)
            if function_code == 4:
                values = self.model.inputs(now)
                current_registers[IN_BASE - start_address : IN_BASE - start_address + 3] = values
        return None

    def _device(self) -> SimDevice:
        return SimDevice(
            id=self.device_id,
            simdata=(
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(OUT_BASE, count=3, values=0, datatype=DataType.REGISTERS)],
                [SimData(IN_BASE, count=3, values=0, datatype=DataType.REGISTERS)],
            ),
            action=self._action,
        )

    def start(self) -> GripperSim:
        self._serving.start(
            lambda: ModbusSerialServer(self._device(), port=self.port, baudrate=self.baudrate, timeout=0.5),
            f"gripper simulator could not open {self.port}")
        return self

    def stop(self) -> None:
        self._serving.stop()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Simulated Robotiq-style gripper on Modbus RTU")
    p.add_argument("--port", required=True, help="serial device, e.g. one end of a socat pty pair")
    p.add_argument("--device-id", type=int, default=9)
    p.add_argument("--baudrate", type=int, default=115200)
    p.add_argument("--object-at", type=int, default=200, help="finger position of the object, -1 for none")
    a = p.parse_args(argv)
    sim = GripperSim(a.port, a.device_id, a.baudrate, a.object_at).start()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    print(f"gripper simulator on {a.port} (device id {a.device_id})", flush=True)
    while not done.wait(0.5):
        pass
    sim.stop()


if __name__ == "__main__":
    main()
