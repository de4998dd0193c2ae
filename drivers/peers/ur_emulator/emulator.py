"""The emulator's servers on the three UR ports and its 500 Hz controller loop; run it as a process."""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import logging
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from drivers.peers.ur_emulator.controller import Controller
from drivers.peers.ur_emulator.dashboard import serve_dashboard
from drivers.peers.ur_emulator.rtde import RtdeConnection
from drivers.peers.ur_emulator.script import serve_script

log = logging.getLogger("cellctl.ur_emulator")

STALL_LOG_S = 0.02
"""A control-loop tick this much later than its period is logged (at most once a second, the worst)."""

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
PORT_LOCK_PATH = "/tmp/cellctl-ur-emulator-ports.lock"
"""File lock held by whoever runs an emulator on 127.0.0.1's fixed UR ports in tests/benchmarks."""


class UrEmulator:
    """The emulator: servers on the three UR ports and the 500 Hz controller loop."""

    def __init__(self, host: str = "127.0.0.1", rtde_port: int = RTDE_PORT,
                 dashboard_port: int = DASHBOARD_PORT, script_ports: tuple[int, ...] = SCRIPT_PORTS,
                 frequency_hz: float = 500.0, speed_slider: float = 1.0) -> None:
        self.host = host
        self.ports = {"rtde": rtde_port, "dashboard": dashboard_port}
        self.script_ports = script_ports
        self.frequency_hz = frequency_hz
        self.controller = Controller()
        self.controller.arm.speed_slider = speed_slider  # the pendant's speed slider (fraction, 0-1]
        self.stopping = threading.Event()
        self._servers: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._rtde_clients: list[RtdeConnection] = []
        self._clients_lock = threading.Lock()
        self._client_socks: list[socket.socket] = []

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Bind every port (raises OSError naming the port when one is taken) and start serving."""
        specs: list[tuple[int, Callable[[socket.socket], None]]] = [
            (self.ports["rtde"], self._serve_rtde), (self.ports["dashboard"], self._serve_dashboard)]
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

    def _spawn(self, target: Callable[..., None], *args: Any) -> None:
        t = threading.Thread(target=target, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept_loop(self, srv: socket.socket, handler: Callable[[socket.socket], None]) -> None:
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

    # -- the servers -------------------------------------------------------------------------------
    def _serve_rtde(self, conn: socket.socket) -> None:
        client = RtdeConnection(conn, self.controller, self.frequency_hz, self.stopping)
        with self._clients_lock:
            self._rtde_clients.append(client)
        try:
            client.serve()
        finally:
            with self._clients_lock:
                if client in self._rtde_clients:
                    self._rtde_clients.remove(client)

    def _serve_script(self, conn: socket.socket) -> None:
        c = self.controller
        serve_script(conn, c.lock, c.arm, c.script, self.stopping)

    def _serve_dashboard(self, conn: socket.socket) -> None:
        serve_dashboard(conn, self.controller, self.stopping)

    def _control_loop(self) -> None:
        period = 1.0 / self.frequency_hz
        tick = 0
        next_t = time.monotonic()
        ctrl = self.controller
        last, worst, told = time.monotonic(), 0.0, time.monotonic()
        while not self.stopping.is_set():
            now = time.monotonic()
            worst = max(worst, now - last - period)  # a tick later than its period: the loop stalled
            last = now
            if worst > STALL_LOG_S and now - told >= 1.0:  # a real controller never stalls: say so, once a second
                log.warning("UR emulator: its 500 Hz loop stalled %.0f ms (the machine's load; the arm and its "
                            "state stream stood meanwhile)", worst * 1e3)
                worst, told = 0.0, now
            with self._clients_lock:
                clients = [c for c in self._rtde_clients if c.started and c.alive]
            packets: list[tuple[RtdeConnection, bytes]] = []
            with ctrl.lock:
                ctrl.step(now)
                for c in clients:
                    if tick % c.output_period_ticks == 0:
                        packets.append((c, c.pack_state(now)))
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
        script_ports: tuple[int, ...] = SCRIPT_PORTS, frequency_hz: float = 500.0, speed_slider: float = 1.0) -> None:
    """Run the emulator until SIGINT or SIGTERM (the entry point of ``cellctl sim ur``)."""
    emulator = UrEmulator(host, rtde_port, dashboard_port, script_ports, frequency_hz, speed_slider)
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
    parser.add_argument("--speed-slider", type=float, default=1.0,
                        help="the pendant's speed slider: moves run at this fraction of the commanded speed (0-1]")
    args = parser.parse_args(argv)
    if not 0 < args.speed_slider <= 1:
        parser.error("--speed-slider must be in (0, 1]")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    run(host=args.host, frequency_hz=args.frequency_hz, speed_slider=args.speed_slider)
