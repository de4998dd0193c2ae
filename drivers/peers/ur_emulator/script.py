"""The script server (ports 30001-30003) and ``ur_rtde``'s control script, as the emulator plays it.

When a script arrives, the emulator plays the control script's part of the register handshake:
program running (robot status bits 0b11, runtime state 2) and output int register 0 = 1 (ready);
a command in input int register 0 runs, output int register 0 = 2 when it is done, back to 1 when
the client clears the command; 255 stops the script. The command codes are ``ur_rtde``'s
``RobotCommand::Type``; ``input_int_register_1`` = 1 marks an asynchronous move.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from drivers.peers.ur_emulator.arm import ROBOT_MODE_NAMES, Arm, T_to_pose, forward_kinematics

log = logging.getLogger("cellctl.ur_emulator")

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

SCRIPT_START_S = 0.15
"""How long after the last script bytes the program counts as started (the controller compiles it)."""


@dataclass
class ControlScript:
    """The control script's state and its RTDE registers (the controller holds the lock)."""

    program_running: bool = False
    receiving_since: float | None = None
    in_int: list[int] = field(default_factory=lambda: [0] * 48)
    in_double: list[float] = field(default_factory=lambda: [0.0] * 48)
    out_int: list[int] = field(default_factory=lambda: [0] * 48)
    out_double: list[float] = field(default_factory=lambda: [0.0] * 48)
    cmd_state: str = "ready"  # ready | busy | done

    def runtime_state(self) -> int:
        return 2 if self.program_running else 1

    def script_arrived(self, arm: Arm, now: float) -> None:
        """Script bytes came in: a new script replaces the running one once it has all arrived."""
        if self.program_running:
            self.stop(arm, "a new script replaces the running one")
        self.receiving_since = now

    def stop(self, arm: Arm, reason: str) -> None:
        if self.program_running:
            log.info("control script stopped: %s", reason)
        self.program_running = False
        arm.motion = None
        self.out_int[0] = 0
        self.cmd_state = "ready"

    def finish_command(self) -> None:
        self.cmd_state = "done"
        self.out_int[0] = 2

    def step(self, arm: Arm, now: float) -> None:
        """Start a script that has arrived, then run the register handshake of one tick."""
        if self.receiving_since is not None and now - self.receiving_since > SCRIPT_START_S:
            self.receiving_since = None
            if arm.ready:
                self.program_running = True
                self.cmd_state = "ready"
                self.out_int[0] = 1
                log.info("control script running")
            else:
                log.warning("control script rejected: robot is not running (mode %s, safety %s)",
                            ROBOT_MODE_NAMES.get(arm.robot_mode), arm.safety_mode)
        if not self.program_running:
            return
        cmd = self.in_int[0]
        if self.cmd_state == "ready" and cmd != CMD_NO_CMD:
            self._start_command(arm, cmd, now)
        elif self.cmd_state == "done" and cmd == CMD_NO_CMD:
            self.cmd_state = "ready"
            self.out_int[0] = 1

    def _start_command(self, arm: Arm, cmd: int, now: float) -> None:
        d = self.in_double
        asynchronous = self.in_int[1] == 1
        if cmd == CMD_STOP_SCRIPT:
            self.stop(arm, "stopScript")
            return
        if cmd in CONTINUOUS_CMDS:
            return  # servo/speed/watchdog streams: the client does not wait for "done"; not simulated
        if cmd in (CMD_MOVEL, CMD_MOVEJ):
            self.cmd_state = "busy"
            start = arm.start_linear if cmd == CMD_MOVEL else arm.start_joint
            if not start(np.array(d[0:6]), d[6], now, not asynchronous):
                self.stop(arm, "inverse kinematics failed or target unreachable")
                return
            if asynchronous:
                self.finish_command()
            return
        if cmd in (CMD_STOPL, CMD_STOPJ):
            arm.halt()
        elif cmd == CMD_PROTECTIVE_STOP:
            arm.protective_stop()
        elif cmd == CMD_FK_DEFAULT:
            self.out_double[0:6] = list(T_to_pose(arm.T))
        elif cmd == CMD_FK_ARGS:
            self.out_double[0:6] = list(T_to_pose(forward_kinematics(np.array(d[0:6]))))
        self.finish_command()


def serve_script(conn: socket.socket, lock: threading.Lock, arm: Arm, script: ControlScript,
                 stopping: threading.Event) -> None:
    """Receive URScript on one connection; each chunk (re)starts the control script."""
    conn.settimeout(0.5)
    received = 0
    with contextlib.suppress(OSError):
        while not stopping.is_set():
            try:
                chunk = conn.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                break
            received += len(chunk)
            with lock:
                script.script_arrived(arm, time.monotonic())
    log.debug("script connection closed after %d bytes", received)
    with contextlib.suppress(OSError):
        conn.close()
