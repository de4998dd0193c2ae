"""A simulated vacuum cup and parallel gripper on Modbus TCP digital I/O, the peer of ``kind: modbus`` grippers.

One remote I/O block with two grippers wired to it (coils are the block's outputs, discrete
inputs its inputs; ``drivers.io.modbus`` addresses channel k at address k):

- coil 0 switches the **vacuum**, coil 1 the **blow-off**; discrete input 0 is the **vacuum
  switch**: on ``rise_s`` after the vacuum comes on while a part is under the cup;
- coil 2 **closes** the parallel gripper, coil 3 **opens** it; discrete input 1 is **closed on
  part**: on ``rise_s`` after it closes (close on, open off) on a part; closing on nothing never
  sets it.

Whether a part is there is the peer's state (``part_present``; ``--no-part`` starts without one).

Run it: ``python -m drivers.peers.modbus_gripper --port 5021`` (listens on 127.0.0.1).
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from dataclasses import dataclass

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.peers.modbus_serving import ServedModbus

VACUUM, BLOW_OFF, CLOSE, OPEN = 0, 1, 2, 3
VACUUM_SWITCH, CLOSED_ON_PART = 0, 1


@dataclass
class GripperIO:
    """The two grippers' mechanics (times from ``time.monotonic``)."""

    rise_s: float = 0.05
    part_present: bool = True
    coils: tuple[bool, bool, bool, bool] = (False, False, False, False)
    vacuum_since: float | None = None
    closed_since: float | None = None

    def write(self, coil: int, value: bool, now: float) -> None:
        c = list(self.coils)
        if 0 <= coil < len(c):
            c[coil] = value
        self.coils = (c[0], c[1], c[2], c[3])
        vac = self.coils[VACUUM] and not self.coils[BLOW_OFF]
        self.vacuum_since = (self.vacuum_since or now) if vac else None
        closed = self.coils[CLOSE] and not self.coils[OPEN]
        self.closed_since = (self.closed_since or now) if closed else None

    def inputs(self, now: float) -> int:
        """The discrete inputs as a bit word (bit k: input k)."""
        vac = self.vacuum_since is not None and self.part_present and now - self.vacuum_since >= self.rise_s
        held = self.closed_since is not None and self.part_present and now - self.closed_since >= self.rise_s
        return (1 << VACUUM_SWITCH if vac else 0) | (1 << CLOSED_ON_PART if held else 0)


class ModbusGripperSim:
    """The Modbus TCP server of the I/O block; ``start()`` runs it in a background thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 5021, device_id: int = 1, part_present: bool = True,
                 rise_s: float = 0.05) -> None:
        self.host, self.port, self.device_id = host, port, device_id
        self.io = GripperIO(rise_s=rise_s, part_present=part_present)
        self._lock = threading.Lock()
        self._serving = ServedModbus("modbus-gripper-sim")

    def set_part(self, present: bool) -> None:
        with self._lock:
            self.io.part_present = present

    def _device(self) -> SimDevice:
        return SimDevice(
            id=self.device_id,
            simdata=(
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(0, count=4, values=0, datatype=DataType.REGISTERS)],
                [SimData(0, count=4, values=0, datatype=DataType.REGISTERS)],
            ),
            action=self._action,
        )

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      current_registers: list[int], set_values: list[int] | list[bool] | None) -> None:
        now = time.monotonic()
        with self._lock:
            if function_code in (5, 15) and set_values is not None:  # coils: the block's outputs
                for i, v in enumerate(set_values):
                    self.io.write(address + i, bool(v), now)
            if function_code == 2:  # discrete inputs: the grippers' switches
                current_registers[0 - start_address] = self.io.inputs(now)
        return None

    def start(self) -> ModbusGripperSim:
        self._serving.start(
            lambda: ModbusTcpServer(self._device(), address=(self.host, self.port)),
            f"Modbus gripper simulator cannot listen on {self.host}:{self.port}")
        return self

    def stop(self) -> None:
        self._serving.stop()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Simulated vacuum cup and parallel gripper on Modbus TCP digital I/O")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=5021)
    p.add_argument("--no-part", action="store_true", help="start with no part under the grippers")
    a = p.parse_args(argv)
    sim = ModbusGripperSim(a.host, a.port, part_present=not a.no_part).start()
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    print(f"gripper I/O simulator on {a.host}:{a.port}", flush=True)
    while not done.wait(0.5):
        pass
    sim.stop()


if __name__ == "__main__":
    main()
