"""Helpers that start and stop the real protocol peers of the driver tests (all on 127.0.0.1)."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

from tests.support.forked import Forked, popen_module
from tests.support.ports import free_port  # noqa: F401  (the peers' tests import it from here)

REPO = Path(__file__).resolve().parents[2]


def fresh_state(robot: Any, timeout_s: float = 5.0) -> Any:
    """``robot.state()`` once a sample within the adapter's age limit is there, polled until ``timeout_s``.

    For set-ups: on a loaded machine one sample can come late (a UR state 0.20 s old against a 0.2 s
    limit), and the adapter rightly refuses it as stale (``DeviceUnavailable``); a set-up waits for the
    next one instead of failing. The adapter's rule is not loosened: a state that stays stale fails here.
    """
    from drivers.base import DeviceUnavailable

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return robot.state()
        except DeviceUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def wait_port(port: int, timeout_s: float = 10.0, host: str = "127.0.0.1") -> None:
    """Wait until something accepts TCP connections on ``host:port``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on {host}:{port} after {timeout_s} s")


class PeerProcess:
    """A peer started as ``python -m module args`` in its own process; stopped by its pid only."""

    def __init__(self, module: str, *args: str, ready_port: int | None = None, ready_text: str | None = None) -> None:
        self.module = module
        self.args = args
        self.ready_port = ready_port
        self.ready_text = ready_text
        self.proc: Forked | subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 15.0) -> PeerProcess:
        """Start the peer (forked from the test process's fork server, ``tests/support/forked.py``, where
        that is the same as an exec); wait for its port to accept, or for ``ready_text`` on its stdout."""
        read_fd, write_fd = os.pipe() if self.ready_text else (-1, subprocess.DEVNULL)
        try:
            self.proc = popen_module(self.module, self.args, cwd=REPO, stdin=subprocess.DEVNULL, stdout=write_fd,
                                     stderr=subprocess.DEVNULL)
        finally:
            if self.ready_text:
                os.close(write_fd)
        if self.ready_port is not None:
            wait_port(self.ready_port, timeout_s)
        if self.ready_text is not None:
            stdout = os.fdopen(read_fd, "rb")
            found = threading.Event()

            def watch() -> None:
                for line in stdout:
                    if self.ready_text and self.ready_text.encode() in line:
                        found.set()

            threading.Thread(target=watch, daemon=True).start()
            if not found.wait(timeout_s):
                raise TimeoutError(f"{self.module} did not print {self.ready_text!r} within {timeout_s} s")
        if self.proc.poll() is not None:  # the port answered, but not ours: another peer holds it
            raise RuntimeError(f"{self.module} exited ({self.proc.returncode}); is another one using its port?")
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def kill(self) -> None:
        """SIGKILL: the peer dies mid-stream, the kernel closes its sockets."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)

    def freeze(self) -> None:
        os.kill(self.pid, signal.SIGSTOP)

    def thaw(self) -> None:
        os.kill(self.pid, signal.SIGCONT)

    def stop(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            os.kill(self.pid, signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc = None


class MjpegServer:
    """An HTTP multipart MJPEG stream on 127.0.0.1 (what IP cameras serve); frame i has grey level i."""

    def __init__(self, port: int = 0, period_s: float = 0.02) -> None:
        self.port = port
        self.period_s = period_s
        self.server: Any = None
        self.alive = threading.Event()
        self.frames_sent = 0

    def start(self) -> MjpegServer:
        import cv2
        import numpy as np

        owner = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                i = 0
                with contextlib.suppress(OSError):
                    while owner.alive.is_set():
                        ok, jpg = cv2.imencode(".jpg", np.full((48, 64, 3), (i * 10) % 256, np.uint8))
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                         % len(jpg) + jpg.tobytes() + b"\r\n")
                        owner.frames_sent += 1
                        i += 1
                        time.sleep(owner.period_s)

            def log_message(self, *args: Any) -> None:
                pass

        ThreadingHTTPServer.allow_reuse_address = True
        self.server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        self.alive.set()
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/stream.mjpg"

    def stop(self) -> None:
        """Stop serving and drop the open streams (the peer dies mid-stream)."""
        self.alive.clear()
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()
            self._thread.join(timeout=5)
            self.server = None
            time.sleep(self.period_s * 3)


class GarbageServer:
    """A TCP peer on 127.0.0.1 that answers every request with bytes that follow no protocol."""

    def __init__(self, port: int = 0, reply: bytes = b"\x00\x07Zgarbage!\xff\xff\x00" * 3) -> None:
        self.reply = reply
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", port))
        self.srv.listen(8)
        self.srv.settimeout(0.1)
        self.port: int = self.srv.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def start(self) -> GarbageServer:
        self._thread.start()
        return self

    def _serve(self) -> None:
        conns: list[socket.socket] = []
        while not self._stop.is_set():
            try:
                c, _ = self.srv.accept()
                c.settimeout(0.05)
                conns.append(c)
                c.sendall(self.reply)
            except TimeoutError:
                pass
            for c in conns:
                with contextlib.suppress(OSError):
                    if c.recv(4096):
                        c.sendall(self.reply)
        for c in conns:
            c.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.srv.close()


class SocatPair:
    """A pseudo-terminal pair from socat: ``a`` and ``b`` are linked serial ports (stopped by pid)."""

    def __init__(self, directory: Path) -> None:
        self.a = directory / "tty-a"
        self.b = directory / "tty-b"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> SocatPair:
        self.proc = subprocess.Popen(["socat", "-d", "-d", f"pty,raw,echo=0,link={self.a}",
                                      f"pty,raw,echo=0,link={self.b}"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5
        while not (self.a.exists() and self.b.exists()):
            if time.monotonic() > deadline:
                raise TimeoutError("socat did not create the pty pair")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=5)
        self.proc = None
        deadline = time.monotonic() + 2
        while (self.a.exists() or self.b.exists()) and time.monotonic() < deadline:
            time.sleep(0.02)


def answers_within(fn: Callable[[], object], timeout_s: float) -> BaseException | None:
    """Run ``fn`` in a thread and wait for it (an event, not a stopwatch): fail the test if it has
    neither returned nor raised within ``timeout_s``; return what it raised (None if it returned)."""
    done = threading.Event()
    box: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, daemon=True).start()
    if not done.wait(timeout_s):
        raise AssertionError(f"no answer within {timeout_s} s")
    return box[0] if box else None
