"""The script server (ports 30001-30003) and ``ur_rtde``'s control script, as the emulator plays it.

When a script arrives, the emulator plays the control script's part of the register handshake:
program running (robot status bits 0b11, runtime state 2) and output int register 0 = 1 (ready);
a command in input int register 0 runs, output int register 0 = 2 when it is done, back to 1 when
the client clears the command; 255 stops the script. ``servoL`` streams move the arm (each pose
reached in the command's ``time``, as the script's servo thread does): host-side conveyor tracking
uses it. The command codes are ``ur_rtde``'s
``RobotCommand::Type``; ``input_int_register_1`` = 1 marks an asynchronous move. The script's
"realtime" commands (servo, speed, ...) are acknowledged at once and not simulated; every other
command, an unknown one too, ends with "done" and waits for the client to clear it, as the script does.

The **RTDE watchdog**: command 35 (``setWatchdog``) arms ``rtde_set_watchdog("input_int_register_0",
f, "stop")`` with f (Hz) from input double register 0. From then on, while the script runs, every
RTDE input package that carries ``input_int_register_0`` (every command ``ur_rtde``'s control
interface sends, and its clears) feeds it; a gap longer than 1/f stops the program, which halts the
arm where it is, and is logged. The watchdog ends with the program, as the controller's does.
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
CMD_SERVO_STOP = 16
CMD_SERVOL = 24
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_FK_DEFAULT = 43
CMD_FK_ARGS = 44
CMD_STOP_SCRIPT = 255
CMD_SET_WATCHDOG = 35
CMD_KICK_WATCHDOG = 99
REALTIME_CMDS = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
"""The control script's realtime commands (servo, speed, force...): ready again at once. Of them only
``servoL`` (24) moves the arm (to each streamed pose in the command's ``time``); the others are not simulated.
Every other command, ``kickWatchdog``'s 99 and ``servoStop``'s 16 among them, is done once and then waits
for a clear."""
SERVO_MIN_TIME_S = 0.002
"""The shortest ``time`` of a servoL step (one 500 Hz controller tick)."""
WATCHDOG_VARIABLE = "input_int_register_0"
"""The input the script's watchdog watches (``ur_rtde`` without its upper register range)."""
WATCHDOG_MAX_TICK_S = 0.01
"""Silence is counted in controller ticks of at most this (s): a stall of the emulator's own process
(a loaded test machine) is not taken for the client's silence, which a real-time controller never sees."""

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
    watchdog_hz: float = 0.0
    """The armed watchdog's minimum input frequency (Hz); 0: none armed."""
    watchdog_silent_s: float = 0.0
    """Controller time since the watched input was last updated (s)."""
    watchdog_fed_s: float = 0.0
    """When it was last updated (``time.monotonic``), for the report."""
    watchdog_trips: int = 0
    """Programs the watchdog has stopped (since the emulator started)."""
    stop_reason: str = ""
    """Why the program last stopped (empty while it runs or before the first)."""
    last_tick_s: float | None = None
    fresh_command: bool = False
    command_arrived_s: float = 0.0
    """When the last command package arrived (``time.monotonic``): a servo step ends ``time`` after it, as on a
    real-time controller, however late this process's next tick comes."""
    """An input package carrying the command register came since the last servoL step (a realtime command
    stays in the register between packages: one servoL package is one step, not one per tick)."""

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
            self.stop_reason = reason
        self.program_running = False
        self.watchdog_hz = 0.0  # "all watchdogs are removed on program stop"
        arm.motion = None
        self.out_int[0] = 0
        self.cmd_state = "ready"

    def finish_command(self) -> None:
        self.cmd_state = "done"
        self.out_int[0] = 2

    def input_updated(self, names: list[str]) -> None:
        """An RTDE input package with ``names`` arrived: it feeds the watchdog if it carries its variable."""
        if WATCHDOG_VARIABLE in names:
            self.fresh_command = True
            self.command_arrived_s = time.monotonic()
            self.watchdog_silent_s = 0.0
            self.watchdog_fed_s = time.monotonic()

    def _check_watchdog(self, arm: Arm, now: float) -> None:
        last, self.last_tick_s = self.last_tick_s, now
        if not (self.program_running and self.watchdog_hz > 0) or last is None:
            return
        self.watchdog_silent_s += min(max(0.0, now - last), WATCHDOG_MAX_TICK_S)
        period_s = 1.0 / self.watchdog_hz
        if self.watchdog_silent_s > period_s:
            moving = arm.motion is not None
            self.watchdog_trips += 1
            log.warning("RTDE watchdog: %s not updated for %.3f s (%.3f s on the host clock; minimum %g Hz): "
                        "program stopped%s", WATCHDOG_VARIABLE, self.watchdog_silent_s,
                        time.monotonic() - self.watchdog_fed_s, self.watchdog_hz,
                        ", the arm halted mid-move" if moving else "")
            self.stop(arm, f"RTDE watchdog: {WATCHDOG_VARIABLE} not updated within {period_s:.3f} s")

    def step(self, arm: Arm, now: float) -> None:
        """Start a script that has arrived, check the watchdog, then run the register handshake of one tick."""
        self._check_watchdog(arm, now)
        if self.receiving_since is not None and now - self.receiving_since > SCRIPT_START_S:
            self.receiving_since = None
            if arm.ready:
                self.program_running = True
                self.stop_reason = ""
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
        if cmd == CMD_SERVOL:
            if not self.fresh_command:
                return  # the same package seen again at the next tick
            self.fresh_command = False
            # servoL(pose, speed, acceleration, time, lookahead, gain): the arm reaches the pose in ``time``
            # (a straight line; the controller's servoj on the pose's inverse kinematics); ready again at once
            late_s = max(0.0, now - self.command_arrived_s)
            if not arm.start_linear(np.array(d[0:6]), 1.0, now, False,
                                    duration_s=max(SERVO_MIN_TIME_S, d[8] - late_s)):
                self.stop(arm, "servoL: inverse kinematics failed or target unreachable")
            return
        if cmd in REALTIME_CMDS:
            return  # speed/force streams: the script is ready again at once; not simulated
        if cmd in (CMD_MOVEL, CMD_MOVEJ):
            self.cmd_state = "busy"
            # moveL/moveJ(target, speed, acceleration, async): the speed in register 6, the acceleration in 7
            started = (arm.start_linear(np.array(d[0:6]), d[6], now, not asynchronous, accel_m_s2=d[7])
                       if cmd == CMD_MOVEL else arm.start_joint(np.array(d[0:6]), d[6], now, not asynchronous))
            if not started:
                self.stop(arm, "inverse kinematics failed or target unreachable")
                return
            if asynchronous:
                self.finish_command()
            return
        if cmd in (CMD_STOPL, CMD_STOPJ, CMD_SERVO_STOP):
            arm.halt()
        elif cmd == CMD_PROTECTIVE_STOP:
            arm.protective_stop()
        elif cmd == CMD_FK_DEFAULT:
            self.out_double[0:6] = list(T_to_pose(arm.T))
        elif cmd == CMD_FK_ARGS:
            self.out_double[0:6] = list(T_to_pose(forward_kinematics(np.array(d[0:6]))))
        elif cmd == CMD_SET_WATCHDOG:
            if not (d[0] > 0 and np.isfinite(d[0])):
                self.stop(arm, f"rtde_set_watchdog: invalid minimum frequency {d[0]!r}")
                return
            self.watchdog_hz = float(d[0])
            self.watchdog_silent_s = 0.0
            log.info("RTDE watchdog armed on %s: minimum %g Hz, action stop", WATCHDOG_VARIABLE, d[0])
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
