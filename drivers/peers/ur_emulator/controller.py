"""The emulated controller's state: the arm and the control script under one lock, stepped at 500 Hz."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

from drivers.peers.ur_emulator.arm import Arm
from drivers.peers.ur_emulator.script import ControlScript


@dataclass
class Controller:
    """Everything the RTDE, dashboard and script servers read or change. Every access is under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    t_start: float = field(default_factory=time.monotonic)
    arm: Arm = field(default_factory=Arm)
    script: ControlScript = field(default_factory=ControlScript)
    input_owners: dict[str, object] = field(default_factory=dict)
    """The RTDE connection that set up each input variable (its only writer while it is connected)."""

    def robot_status_bits(self) -> int:
        return (1 if self.arm.powered else 0) | (2 if self.script.program_running else 0)

    def step(self, now: float) -> None:
        """One controller tick: advance the motion, then the control script's handshake."""
        finished = self.arm.step(now)
        if finished is not None and finished.waiting_client and self.script.cmd_state == "busy":
            self.script.finish_command()
        self.script.step(self.arm, now)
