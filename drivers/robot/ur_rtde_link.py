"""The ``ur_rtde`` adapter's links to its worker processes: the supervised state stream and control.

``StateLink`` runs the state worker (``ur_rtde_worker.state_worker``) under a supervisor thread
that restarts a dead or silent worker with exponential back-off and counts the outages (telling
``on_outage`` when a worker that streamed dies or stalls: the controller is lost, not a late
sample). ``ControlLink`` sends one request at a time to the control worker with a deadline and
kills a worker that misses it (the worker kicks the controller's RTDE watchdog between requests).
Every worker process is started by the supervisor thread (a long-lived thread: the workers'
``PR_SET_PDEATHSIG`` follows the thread that started them).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.context import SpawnContext, SpawnProcess
from typing import TYPE_CHECKING, Any, TypeVar

from drivers.backoff import Backoff, Outages
from drivers.errors import DeviceOperationError, DeviceTimeout, DeviceUnavailable
from drivers.robot.ur_rtde_worker import StateBuffer, control_worker, state_worker
from drivers.robot.ur_track_stream import TrackShared

if TYPE_CHECKING:
    from drivers.robot.ur_rtde_settings import URRTDESettings

T = TypeVar("T")
log = logging.getLogger(__name__)


class StateLink:
    """The state worker, its shared memory, and the supervisor thread that keeps it running."""

    def __init__(self, robot_id: str, config: URRTDESettings, ctx: SpawnContext,
                 on_outage: Callable[[str], None] | None = None) -> None:
        self.robot_id = robot_id
        self.config = config
        self.on_outage = on_outage
        """Called (in the supervisor thread) with the reason when a streaming worker dies or stalls."""
        self._ctx = ctx
        self.buffer = StateBuffer(ctx)
        self.outages = Outages()
        self._backoff = Backoff(config.reconnect_initial_s, config.reconnect_max_s)
        self._stop_worker = ctx.Event()
        self._proc: SpawnProcess | None = None
        self._supervisor: threading.Thread | None = None
        self._closing = threading.Event()
        self._calls: queue.Queue[Callable[[], None]] = queue.Queue()
        self._start_lock = threading.Lock()
        self._last_seq = 0.0
        self._last_seq_change = 0.0
        self._streaming = False
        self.reason = "not connected"

    @property
    def running(self) -> bool:
        """True between ``start`` and ``stop`` (the supervisor keeps reconnecting meanwhile)."""
        return self._supervisor is not None

    def start(self) -> None:
        with self._start_lock:
            if self._supervisor is not None:
                return
            self._closing.clear()
            self._backoff.reset()
            self._supervisor = threading.Thread(target=self._supervise, name=f"ur-{self.robot_id}", daemon=True)
            self._supervisor.start()

    def stop(self) -> None:
        """Stop the worker and then the supervisor; safe to call twice."""
        self._closing.set()
        sup = self._supervisor
        if sup is not None and sup is not threading.current_thread():
            sup.join(timeout=2.0)
        self._supervisor = None
        self._kill_worker()

    def call_in_supervisor(self, fn: Callable[[], T], timeout_s: float = 5.0) -> T:
        """Run ``fn`` in the supervisor thread (worker processes are started there) and return its result."""
        if threading.current_thread() is self._supervisor:
            return fn()
        if self._supervisor is None:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected (call connect())")
        done = threading.Event()
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["value"] = fn()
            except BaseException as exc:  # noqa: BLE001 - handed back to the caller below
                box["error"] = exc
            finally:
                done.set()

        self._calls.put(run)
        if not done.wait(timeout_s):
            raise DeviceTimeout(f"robot {self.robot_id}: the adapter's supervisor did not answer in {timeout_s} s")
        if "error" in box:
            raise box["error"]
        value: T = box["value"]
        return value

    # -- freshness -----------------------------------------------------------------------------------
    def fresh_age(self) -> float | None:
        """Age (s) of the newest sample when it is fresh (and its worker has not lost the controller), else None."""
        age = self.buffer.age_s()
        return age if age is not None and age <= self.config.state_max_age_s and not self.failure else None

    def note_staleness(self) -> None:
        """Open an outage (counted once) when the newest sample is too old; the supervisor closes it."""
        age = self.buffer.age_s()
        if age is not None and age > self.config.state_max_age_s:
            stale_since = time.monotonic() - (age - self.config.state_max_age_s)
            reason = self.reason or (f"no new RTDE state from {self.config.host} for {age:.2f} s "
                                     f"(limit {self.config.state_max_age_s:g} s)")
            self.outages.down(reason, since_s=stale_since)

    @property
    def failure(self) -> str:
        """Why the current worker gave up (connection refused or lost); empty while it works."""
        return self.buffer.error

    # -- the worker ----------------------------------------------------------------------------------
    def _start_worker(self) -> None:
        self.buffer.clear_error()
        self._stop_worker.clear()
        proc = self._ctx.Process(
            target=state_worker, name=f"ur-state-{self.robot_id}", daemon=True,
            args=(self.config.host, self.config.frequency_hz, self.buffer, self._stop_worker, os.getpid()),
        )
        proc.start()
        self._proc = proc
        self._streaming = False
        self._last_seq_change = time.monotonic()

    def _kill_worker(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        self._stop_worker.set()
        proc.join(timeout=0.3)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=2.0)

    def _supervise(self) -> None:
        # This thread must outlive every worker it starts (their PR_SET_PDEATHSIG follows it): it
        # survives any error of one round and ends only with stop().
        with contextlib.suppress(Exception):
            self._start_worker()
        while not self._closing.is_set():
            try:
                self._calls.get(timeout=0.02)()
                continue
            except queue.Empty:
                pass
            try:
                self._check_worker()
            except Exception as exc:  # noqa: BLE001 - logged; the next round tries again
                self.reason = f"supervisor error: {type(exc).__name__}: {exc}"
                log.exception("robot %s: RTDE supervisor round failed", self.robot_id)
        self._kill_worker()

    def _lost(self) -> None:
        """The worker is dead or stalled: restart it later; a stream that had worked is a lost controller."""
        self._kill_worker()
        self._backoff.schedule()
        if self._streaming and self.on_outage is not None:
            self._streaming = False
            self.on_outage(self.reason)

    def _check_worker(self) -> None:
        now = time.monotonic()
        seq = self.buffer.seq
        self.note_staleness()
        if seq != self._last_seq:
            self._last_seq = seq
            self._last_seq_change = now
            self._streaming = True
            self._backoff.reset()
            self.outages.up()
            self.reason = ""
            return
        proc = self._proc
        if proc is not None and proc.is_alive():
            silent_s = now - self._last_seq_change
            # a new worker gets the connect timeout to produce its first sample
            allowed_s = self.config.stall_timeout_s if self._streaming else self.config.connect_timeout_s
            if silent_s < allowed_s:
                return
            self.reason = (f"no RTDE data from {self.config.host} for {silent_s:.1f} s "
                           "(controller frozen or network down)")
            self._lost()
        elif proc is not None:
            self.reason = self.buffer.error or f"RTDE worker for {self.config.host} exited"
            self._lost()
        if self._proc is None and self._backoff.due():
            self.outages.reconnected()
            self._start_worker()


class ControlLink:
    """The control worker: one ``(op, args)`` request at a time, each with a deadline."""

    def __init__(self, robot_id: str, host: str, frequency_hz: float, watchdog_hz: float, ctx: SpawnContext,
                 spawn_in: Callable[[Callable[[], SpawnProcess]], SpawnProcess]) -> None:
        self.robot_id = robot_id
        self.host = host
        self.frequency_hz = frequency_hz
        self.watchdog_hz = watchdog_hz
        self._ctx = ctx
        self._spawn_in = spawn_in
        self._lock = threading.Lock()
        self._proc: SpawnProcess | None = None
        self._conn: Connection | None = None
        self.track = TrackShared(ctx)
        """Conveyor tracking's shared state with the worker's servo stream (``ur_track_stream``)."""

    @property
    def started(self) -> bool:
        return self._proc is not None

    def close(self, graceful: bool = False) -> None:
        """Stop the worker (asking it to disconnect first when ``graceful``); safe to call twice."""
        proc, conn = self._proc, self._conn
        self._proc, self._conn = None, None
        if conn is not None:
            if graceful and proc is not None and proc.is_alive():
                with contextlib.suppress(OSError, ValueError):
                    conn.send(("close", ()))
                    if conn.poll(1.5):
                        conn.recv()
            with contextlib.suppress(OSError):
                conn.close()
        if proc is not None:
            proc.join(timeout=0.5 if graceful else 0.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)

    def _ensure_worker(self) -> Connection:
        if self._proc is not None and self._proc.is_alive() and self._conn is not None:
            return self._conn
        self.close()
        parent, child = self._ctx.Pipe()

        def spawn() -> SpawnProcess:
            proc = self._ctx.Process(target=control_worker, name=f"ur-control-{self.robot_id}", daemon=True,
                                     args=(self.host, self.frequency_hz, self.watchdog_hz, child, os.getpid(),
                                           self.track))
            proc.start()
            return proc

        self._proc = self._spawn_in(spawn)
        child.close()
        self._conn = parent
        return parent

    def prestart(self) -> None:
        """Start the worker process now (its interpreter boots while nothing waits on it)."""
        with self._lock:
            self._ensure_worker()

    def request(self, op: str, args: tuple[Any, ...], timeout_s: float) -> Any:
        """Run one ur_rtde control/dashboard call in the worker; typed errors on failure or deadline."""
        with self._lock:
            conn = self._ensure_worker()
            try:
                conn.send((op, args))
                reply = conn.recv() if conn.poll(timeout_s) else None
            except (OSError, EOFError) as exc:
                self.close()
                raise DeviceUnavailable(
                    f"robot {self.robot_id}: control connection to {self.host} died during {op}; "
                    "it is restarted on the next command") from exc
            if reply is None:
                self.close()
                raise DeviceTimeout(
                    f"robot {self.robot_id}: {op} got no answer from {self.host} within {timeout_s:.1f} s; "
                    "the control connection was reset, check the controller")
        status, value = reply
        if status == "error":
            raise DeviceOperationError(f"robot {self.robot_id}: {op} failed on {self.host}: {value}")
        return value
