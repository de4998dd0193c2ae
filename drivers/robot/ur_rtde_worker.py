"""The child processes of the ``ur_rtde`` adapter and the shared memory they publish state in.

Public interface (what ``ur_rtde.py`` uses): ``StateBuffer`` (the newest sample, written by the
state worker, read by the adapter without blocking), ``StateSample``, ``state_worker`` and
``control_worker`` (process targets).

A worker dies with the process that owns the adapter: it asks the kernel for SIGKILL when its
parent thread ends (``PR_SET_PDEATHSIG``; the adapter starts workers from its long-lived
supervisor thread) and exits at once if its parent is already gone. ``ur_rtde`` may block with
the GIL held, so no Python-level watcher could be relied on.

The control worker arms the controller's **RTDE watchdog** before every move (``setWatchdog``:
the control script stops, and the arm with it, when no input update arrives within 1/f s) and
then kicks it (``kickWatchdog``) several times per period for as long as the control script runs
(the script keeps a watchdog until it stops). The kicks come from this process, so when the
service dies (its workers with it, above) the kicks stop and the controller halts the arm.

Kept free of numpy/scipy/pydantic imports so that a worker starts in well under a second: a
reconnect after an outage is one new process. (``spawn`` also imports the parent's main script in
each worker, without running its ``if __name__ == "__main__"`` block: entry scripts that import
heavy modules at their top slow every worker's start.)
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.context import SpawnContext
from typing import Any

from drivers.robot.ur_track_stream import PERIOD, TrackShared, stream_step

PR_SET_PDEATHSIG = 1

# shared-memory layout of the newest sample (doubles)
_SEQ, _HOST_T, _ROBOT_T, _POSE, _Q, _QD, _TCP_SPEED = 0, 1, 2, 3, 9, 15, 21
_ROBOT_MODE, _SAFETY_MODE, _RUNTIME, _STATUS_BITS, _DIN, _DOUT, _HEARTBEAT, _CONNECTED = range(27, 35)
_SIZE = 36


@dataclass(frozen=True)
class StateSample:
    """One RTDE sample: UR pose vector (m, rad), joints (rad, rad/s), TCP speed (m/s, rad/s), modes."""

    host_time_s: float
    """When it arrived, seconds since the Unix epoch (host clock)."""
    controller_time_s: float
    pose: tuple[float, ...]
    q: tuple[float, ...]
    qd: tuple[float, ...]
    tcp_speed: tuple[float, ...]
    robot_mode: int
    safety_mode: int
    runtime_state: int
    digital_in: int
    digital_out: int


class StateBuffer:
    """The newest sample in shared memory: one writer (the state worker), readers in the adapter."""

    def __init__(self, ctx: SpawnContext) -> None:
        self._shm: Any = ctx.Array(ctypes.c_double, _SIZE)
        self._error: Any = ctx.Array(ctypes.c_char, 256)

    # -- reader side -----------------------------------------------------------------------------
    @property
    def seq(self) -> float:
        """Advances with every new sample."""
        return float(self._shm[_SEQ])

    def age_s(self) -> float | None:
        """Seconds since the newest sample arrived; None before the first."""
        host_t = float(self._shm[_HOST_T])
        return None if host_t == 0.0 else time.time() - host_t

    def snapshot(self) -> StateSample | None:
        """The newest sample, read consistently; None before the first."""
        with self._shm.get_lock():
            s = list(self._shm[:])
        if s[_HOST_T] == 0.0:
            return None
        return StateSample(
            host_time_s=s[_HOST_T], controller_time_s=s[_ROBOT_T], pose=tuple(s[_POSE:_POSE + 6]),
            q=tuple(s[_Q:_Q + 6]), qd=tuple(s[_QD:_QD + 6]), tcp_speed=tuple(s[_TCP_SPEED:_TCP_SPEED + 6]),
            robot_mode=int(s[_ROBOT_MODE]), safety_mode=int(s[_SAFETY_MODE]), runtime_state=int(s[_RUNTIME]),
            digital_in=int(s[_DIN]), digital_out=int(s[_DOUT]),
        )

    @property
    def error(self) -> str:
        """Why the last state worker gave up (empty if it did not say)."""
        return bytes(self._error.value).decode(errors="replace")

    def clear_error(self) -> None:
        self._error.value = b""

    # -- writer side (the state worker) --------------------------------------------------------------
    def set_error(self, message: str) -> None:
        self._error.value = message.encode()[:255]

    def publish(self, host_time_s: float, values: list[float]) -> None:
        """Store a new sample: controller time, pose, q, qd, TCP speed, modes and IO bits, in layout order."""
        with self._shm.get_lock():
            self._shm[_HOST_T] = host_time_s
            self._shm[_ROBOT_T:_DOUT + 1] = values
            self._shm[_SEQ] += 1
            self._shm[_CONNECTED] = 1.0

    def beat(self, host_time_s: float) -> None:
        self._shm[_HEARTBEAT] = host_time_s


# -- child processes --------------------------------------------------------------------------------


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when the thread that started it ends; exit now if the parent is gone."""
    with contextlib.suppress(OSError, AttributeError, TypeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request above took effect
        os._exit(0)


def _quiet_stdout() -> None:
    """ur_rtde prints to stdout; keep it off the caller's stdout (CLI JSON) by sending it to stderr."""
    with contextlib.suppress(OSError):
        os.dup2(2, 1)


def state_worker(host: str, frequency_hz: float, buffer: StateBuffer, stop: Any, parent_pid: int) -> None:
    """Receive RTDE state and publish every new sample in ``buffer`` until ``stop`` is set."""
    _die_with_parent(parent_pid)
    _quiet_stdout()
    try:
        import rtde_receive

        receiver = rtde_receive.RTDEReceiveInterface(host, frequency_hz)
    except Exception as exc:  # ur_rtde raises RuntimeError / boost errors of every kind
        buffer.set_error(f"cannot connect RTDE to {host}:30004: {exc}")
        return
    period = 1.0 / frequency_hz
    last_ts = -1.0
    while not stop.is_set():
        try:
            if not receiver.isConnected():
                buffer.set_error(f"RTDE connection to {host} lost")
                return
            ts = receiver.getTimestamp()
            now = time.time()
            if ts != last_ts:
                last_ts = ts
                buffer.publish(now, [
                    ts,
                    *receiver.getActualTCPPose(),
                    *receiver.getActualQ(),
                    *receiver.getActualQd(),
                    *receiver.getActualTCPSpeed(),
                    receiver.getRobotMode(),
                    receiver.getSafetyMode(),
                    receiver.getRuntimeState(),
                    receiver.getRobotStatus(),
                    receiver.getActualDigitalInputBits(),
                    receiver.getActualDigitalOutputBits(),
                ])
            buffer.beat(now)
        except Exception as exc:
            buffer.set_error(f"RTDE receive failed: {exc}")
            return
        time.sleep(period / 2)
    with contextlib.suppress(Exception):
        receiver.disconnect()


STREAM_NICE = -10
"""The control worker's priority once it streams servo steps, where the service may raise it (root or
CAP_SYS_NICE; otherwise it stays as it is): a late step is a tracking error."""
SCRIPT_START_S = 3.0
"""How long a re-uploaded control script may take to start before a move is sent anyway."""
KICKS_PER_WATCHDOG_PERIOD = 5
"""Kicks sent per watchdog period (1/f): a few late or lost ones do not stop the arm."""


class _Clients:
    """The control worker's ur_rtde clients, (re)connected on first use, and the watchdog they kick."""

    def __init__(self, host: str, frequency_hz: float, watchdog_hz: float) -> None:
        self.host = host
        self.frequency_hz = frequency_hz
        self.watchdog_hz = watchdog_hz
        self.watchdog_armed = False
        """True while the running control script has our watchdog (a new or restarted script has none)."""
        self.last_kick_s = 0.0
        self.ctrl: Any = None
        self.io: Any = None
        self.dash: Any = None

    @property
    def kick_period_s(self) -> float:
        return 1.0 / (self.watchdog_hz * KICKS_PER_WATCHDOG_PERIOD)

    def control(self) -> Any:
        if self.ctrl is None or not self.ctrl.isConnected():
            import rtde_control

            self.watchdog_armed = False
            self.ctrl = rtde_control.RTDEControlInterface(self.host, self.frequency_hz)
        elif not self.ctrl.isProgramRunning():
            self.watchdog_armed = False
            self.ctrl.reuploadScript()
            # Wait for the script to run (a fixed 0.3 s was too short on a loaded machine: the next
            # move was refused); past the deadline the move goes out and is refused with the reason.
            deadline = time.monotonic() + SCRIPT_START_S
            while not self.ctrl.isProgramRunning() and time.monotonic() < deadline:
                time.sleep(0.02)
        return self.ctrl

    def _armed_control(self) -> Any:
        """The control interface with the watchdog armed in its script: no move is sent without it."""
        ctrl = self.control()
        if not self.watchdog_armed:
            if not ctrl.setWatchdog(self.watchdog_hz):
                raise RuntimeError(f"the controller did not arm the RTDE watchdog ({self.watchdog_hz:g} Hz); "
                                   "the move was not sent")
            self.watchdog_armed = True
            self.last_kick_s = time.monotonic()
        return ctrl

    def kick_if_due(self) -> None:
        """Kick the armed watchdog when a kick period has passed since the last one."""
        if not self.watchdog_armed or time.monotonic() - self.last_kick_s < self.kick_period_s:
            return
        self.last_kick_s = time.monotonic()
        try:
            alive = self.ctrl is not None and self.ctrl.isConnected() and self.ctrl.kickWatchdog()
        except Exception:  # noqa: BLE001 - a lost connection: the next move reconnects and arms again
            alive = False
        if not alive:  # the script stopped (its watchdog with it) or the connection is gone
            self.watchdog_armed = False

    def io_interface(self) -> Any:
        if self.io is None or not self.io.isConnected():
            import rtde_io

            self.io = rtde_io.RTDEIOInterface(self.host)
        return self.io

    def dashboard(self) -> Any:
        if self.dash is None or not self.dash.isConnected():
            import dashboard_client

            self.dash = dashboard_client.DashboardClient(self.host)
            self.dash.connect()
        return self.dash

    def run(self, op: str, args: tuple[Any, ...]) -> Any:
        if op == "moveL":
            return self._armed_control().moveL(*args)
        if op == "moveJ":
            return self._armed_control().moveJ(*args)
        if op == "track_begin":  # the stream (ur_track_stream.py) runs from the worker's loop from now
            self._armed_control()
            with contextlib.suppress(OSError):  # a servo stream is soft real time: ask for priority where allowed
                os.setpriority(os.PRIO_PROCESS, 0, STREAM_NICE)
            return True
        if op == "servoStop":
            return None if self.ctrl is None else self.ctrl.servoStop(*args)
        if op in ("stopL", "stopJ"):
            # nothing to stop when no control connection was ever made
            return None if self.ctrl is None else getattr(self.ctrl, op)(*args)
        if op == "fk":
            return list(self.control().getForwardKinematics(*args))
        if op == "digital_out":
            return self.io_interface().setStandardDigitalOut(*args)
        if op == "dashboard":
            return getattr(self.dashboard(), args[0])()
        raise ValueError(f"unknown control request {op!r}")

    def disconnect(self) -> None:
        for obj in (self.ctrl, self.io, self.dash):
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.disconnect()


def control_worker(host: str, frequency_hz: float, watchdog_hz: float, conn: Connection, parent_pid: int,
                   track: TrackShared | None = None) -> None:
    """Answer ``(op, args)`` requests on ``conn`` with ``("ok", result)`` or ``("error", text)``;
    between requests, kick the controller's watchdog while it is armed, and while a conveyor is tracked
    (``track_begin`` until the service ends it, a stop, or a pose outside the envelope) stream its servo
    steps (``ur_track_stream``; their packages feed the watchdog)."""
    _die_with_parent(parent_pid)
    _quiet_stdout()
    clients = _Clients(host, frequency_hz, watchdog_hz)
    streaming, next_step = False, 0.0
    while True:
        try:
            if streaming:
                wait_s: float | None = max(0.0, next_step - time.monotonic())
            else:
                wait_s = clients.kick_period_s if clients.watchdog_armed else None
            ready = conn.poll(wait_s)
            if streaming and time.monotonic() >= next_step and track is not None:
                try:
                    streaming = stream_step(clients.ctrl, track)
                except Exception:  # noqa: BLE001 - a lost connection: the stream ends, the service sees it
                    track.write(active=0.0, failed=2.0)
                    streaming = False
                next_step = max(next_step + float(track.read()[PERIOD]), time.monotonic())
            if not ready:
                if not streaming:
                    clients.kick_if_due()
                continue
            op, args = conn.recv()
        except (EOFError, OSError):
            break
        if op == "close":
            conn.send(("ok", None))
            break
        if op in ("stopL", "stopJ", "servoStop", "track_end", "moveL", "moveJ"):
            streaming = False  # a stop (or any move) ends the stream before it runs
        try:
            result = None if op == "track_end" else clients.run(op, args)
            if op == "track_begin" and track is not None:
                streaming, next_step = True, time.monotonic()
            conn.send(("ok", result))
        except Exception as exc:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        if not streaming:
            clients.kick_if_due()
    clients.disconnect()
