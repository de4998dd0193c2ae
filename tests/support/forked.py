"""``cellctl`` runs for the tests as forks of a pre-imported process: real processes, without the imports.

A fresh ``cellctl`` pays about 3 s of CPU importing numpy, scipy, OpenCV, numba, FastAPI and the
service's pydantic models before it does anything; the suite starts about a hundred served cells
and many CLI runs. Each test process (an xdist worker) therefore starts one fork server
(``tests/support/forkserver.py``) on first use, which imports all that once; ``popen_cellctl`` and
``run_cellctl`` then have it fork a child that takes the call's environment, working directory,
stdin/stdout/stderr and argv and runs the ``cellctl`` console script. The child is a separate
process with its own pid, as an exec'd ``cellctl`` is: signals, ``kill -9``, exit codes and logs
work on it as before, through a ``Popen``-like handle (:class:`Forked`).

What a fork cannot reproduce, an exec does (the call falls back to ``subprocess``, same answers):

- an environment that differs from the server's in a variable read at import time. Only the
  variables in :data:`READ_AT_USE` may differ (``cellctl`` reads its own ``CELLCTL_*``, ``HOME``
  and ``XDG_*`` when it uses them, never at import: ``tests/test_forked.py`` holds that); anything
  else, e.g. ``NUMBA_CACHE_DIR`` (numba reads it at import), means an exec;
- ``CELLCTL_TEST_FORK=0`` in the environment: every run is exec'd (to compare, or to rule the fork
  server out).

Tests whose point is the console script itself keep exec'ing it (``subprocess`` with
``tests.support.served.CELLCTL``): the README's commands, the start-up import checks, the installed
entry point (docs/testing.md lists them).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from tests.support.forkserver import HEADER

CELLCTL = str(Path(sys.executable).with_name("cellctl"))
REPO = Path(__file__).resolve().parents[2]
READ_AT_USE = ("CELLCTL_", "PYTEST_", "HOME", "XDG_DATA_HOME", "XDG_CONFIG_HOME", "XDG_RUNTIME_DIR")
"""Environment variables (names or prefixes) a forked run may set differently from its fork server:
read by ``cellctl`` when used, not at import (pytest's own are for the test process only)."""
SET_BY_IMPORT = ("LD_LIBRARY_PATH",)
"""Variables an import sets in ``os.environ`` (``import cv2`` appends its own library folder), so they
differ between a process that imported it and one that has not yet, whatever the run asked for; the
dynamic loader reads them once, at a process's start (a forked run has the server's libraries loaded
already), and a forked run's own children get the run's environment as given."""
START_TIMEOUT_S = 120.0
SHARED = "CELLCTL_TEST_FORK_SHARED"
"""``<owner pid>:<folder>``, set by the run's pytest process (``tests/conftest.py``): one fork server for
the run's test processes (the xdist workers), listening in the folder, started by the first that needs it
and ending when the owner exits. Without it (or set to ``0``) each process starts its own."""

Stdio = int | IO[Any] | None
forked_cpu_s = 0.0
"""User + system CPU seconds of this process's forked ``cellctl`` runs that have ended and been waited
for (the fork server's children are not this process's: ``getrusage(RUSAGE_CHILDREN)`` misses them
until the server exits; ``tests/support/cpu_report.py`` adds this)."""
live: set[int] = set()
"""Pids of this process's forked runs still running (``tests/support/cpu_report.py`` reads their CPU)."""


class Forked:
    """A forked ``cellctl``: ``pid``, ``poll``, ``wait``, ``send_signal``, ``terminate``, ``kill``,
    ``returncode`` (negative: the signal that ended it), as ``subprocess.Popen`` has them."""

    stdin = stdout = stderr = None

    def __init__(self, args: list[str], pid: int, pidfd: int, conn: socket.socket) -> None:
        self.args = args
        self.pid = pid
        self.returncode: int | None = None
        self._pidfd: int | None = pidfd
        self._conn = conn
        self._status = b""
        live.add(pid)

    def _readable(self, timeout_s: float | None) -> bool:
        return bool(select.select([self._conn], [], [], timeout_s)[0])

    def _collect(self) -> None:
        """Read the wait status the server sends when the child ends (or notice the server is gone)."""
        while not self._status.endswith(b"\n"):
            more = self._conn.recv(64)
            if not more:
                raise RuntimeError(f"the fork server went away before {self.args} ended (pid {self.pid})")
            self._status += more
        status, cpu_s = self._status.split()
        self.returncode = os.waitstatus_to_exitcode(int(status))
        global forked_cpu_s
        forked_cpu_s += float(cpu_s)
        live.discard(self.pid)
        self._conn.close()
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None

    def poll(self) -> int | None:
        if self.returncode is None and self._readable(0):
            self._collect()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            if not self._readable(timeout):
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            self._collect()
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        self.poll()
        if self.returncode is None and self._pidfd is not None:
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile, as Popen.send_signal
                signal.pidfd_send_signal(self._pidfd, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def __enter__(self) -> Forked:
        return self

    def __exit__(self, *exc: object) -> None:
        self.wait()


class ForkServer:
    """The fork server this process uses: its own (started now, ended when this process exits), or the
    run's shared one (``shared``: its folder), which the run's pytest process started (:func:`share_server`)."""

    def __init__(self, shared: str | None = None) -> None:
        self.shared = shared is not None
        self.dir = shared if shared is not None else tempfile.mkdtemp(prefix="cellctl-fork-")
        self.path = os.path.join(self.dir, "s")
        self.pid = os.getpid()
        if shared is not None:
            self.server_pid = int(Path(self.dir, "pid").read_text())
            self.process: subprocess.Popen[bytes] | None = None
            self._wait_listening()
            self.env = json.loads(Path(self.path + ".env.json").read_text())  # what it was started with
            return
        self.process = _start_server(self.dir, server_env())
        self.env, self.server_pid = server_env(), self.process.pid
        assert self.process.stdout is not None
        ready = select.select([self.process.stdout], [], [], START_TIMEOUT_S)[0]
        if not ready or self.process.stdout.readline() != b"ready\n":
            self.close()
            raise RuntimeError(f"the fork server did not start: {Path(self.dir, 'server.log').read_text()}")

    def _wait_listening(self) -> None:
        """Wait until the shared server listens (it binds its socket once its imports are done)."""
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
                try:
                    probe.connect(self.path)
                    return
                except (FileNotFoundError, ConnectionRefusedError):
                    pass
            if time.monotonic() > deadline or not os.path.exists(f"/proc/{self.server_pid}"):
                raise RuntimeError(f"the run's fork server did not start: {Path(self.dir, 'server.log').read_text()}")
            time.sleep(0.05)

    def can_fork(self, env: Mapping[str, str]) -> bool:
        """Whether a child with ``env`` behaves as an exec'd one (no import-time variable differs)."""
        keys = set(env) | set(self.env)
        return all(env.get(k) == self.env.get(k) for k in keys if not k.startswith(READ_AT_USE + SET_BY_IMPORT))

    def spawn(self, args: list[str], env: Mapping[str, str], cwd: str, fds: Sequence[int]) -> Forked:
        body = json.dumps({"argv": args, "env": dict(env), "cwd": cwd}).encode()
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(self.path)
            socket.send_fds(conn, [HEADER.pack(len(body)) + body], list(fds))
            reply = b""
            pidfds: list[int] = []
            while not reply.endswith(b"\n"):
                data, got, _flags, _addr = socket.recv_fds(conn, 64, 1)
                if not data:
                    raise RuntimeError(f"the fork server refused {args}: {Path(self.dir, 'server.log').read_text()}")
                reply += data
                pidfds += got
        except BaseException:
            conn.close()
            raise
        return Forked(args, int(reply), pidfds[0], conn)

    def close(self) -> None:
        """End this process's own server (the shared one is ended by the run's pytest process)."""
        if self.process is not None:
            _end_server(self.process, self.dir)


def server_env() -> dict[str, str]:
    """The environment a fork server runs with: this process's, without the variables read at use."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("CELLCTL_", "PYTEST_"))}


def _start_server(folder: str, env: dict[str, str] | None) -> subprocess.Popen[bytes]:
    """A fork server listening in ``folder``, with ``env`` (None: this process's, as its other children
    get it); it ends when its stdin closes."""
    with open(os.path.join(folder, "server.log"), "ab") as log:
        return subprocess.Popen([sys.executable, "-m", "tests.support.forkserver", os.path.join(folder, "s")],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, cwd=REPO, env=env)


def _end_server(process: subprocess.Popen[bytes], folder: str) -> None:
    """Close the server's stdin (it exits; its running children go on), wait for it, remove its folder."""
    if process.stdin is not None:
        process.stdin.close()
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    if process.stdout is not None:
        process.stdout.close()
    shutil.rmtree(folder, ignore_errors=True)


_server: ForkServer | None = None


def fork_server() -> ForkServer | None:
    """This process's fork server (the run's shared one, or its own; started now if need be), or None
    when runs are to be exec'd."""
    global _server
    if os.environ.get("CELLCTL_TEST_FORK", "1") == "0":
        return None
    if _server is None or _server.pid != os.getpid():
        _server = ForkServer(shared_server())
        atexit.register(_server.close)
    return _server


def shared_server() -> str | None:
    """The folder of the run's shared fork server (:data:`SHARED`), if its owner still runs."""
    owner, _, folder = os.environ.get(SHARED, "").partition(":")
    if not owner.isdigit() or not os.path.isdir(folder) or not os.path.exists(f"/proc/{owner}"):
        return None
    return folder


def share_server() -> subprocess.Popen[bytes] | None:
    """Called by the run's pytest process before it starts its xdist workers: start the one fork server
    they share (in the background: a worker that needs it waits until it listens) and tell them where
    (:data:`SHARED`); None where runs are exec'd, one server per process is asked for
    (``CELLCTL_TEST_FORK_SHARED=0``), or this pytest runs inside a run that shares one already. End it
    with :func:`end_shared` (it is this process's child: its CPU and its children's count as the run's)."""
    if os.environ.get("CELLCTL_TEST_FORK", "1") == "0" or os.environ.get(SHARED) == "0" \
            or shared_server() is not None:
        return None
    folder = tempfile.mkdtemp(prefix="cellctl-fork-")
    # the environment the workers get too (xdist starts them with this process's: a library's setenv in C,
    # e.g. readline's COLUMNS and LINES, is in it though not in os.environ); the server writes it down
    process = _start_server(folder, None)
    Path(folder, "pid").write_text(str(process.pid))
    os.environ[SHARED] = f"{os.getpid()}:{folder}"
    return process


def end_shared(process: subprocess.Popen[bytes]) -> None:
    """End the run's shared fork server (forked runs still running go on) and remove its folder."""
    folder = shared_server()
    os.environ.pop(SHARED, None)
    if folder is not None:
        _end_server(process, folder)


def _fd(stream: Stdio, default: int, opened: list[int]) -> int:
    if stream is None:
        return default
    if isinstance(stream, int):
        if stream == subprocess.DEVNULL:
            fd = os.open(os.devnull, os.O_RDWR)
            opened.append(fd)
            return fd
        return stream
    return stream.fileno()


def popen_cellctl(args: Sequence[str], env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                  stdin: Stdio = None, stdout: Stdio = None, stderr: Stdio = None) -> Forked | subprocess.Popen[bytes]:
    """``subprocess.Popen([cellctl, *args], ...)``, forked from the fork server where that is the same."""
    return _popen([CELLCTL, *args], env, cwd, stdin, stdout, stderr)


def popen_module(module: str, args: Sequence[str], env: Mapping[str, str] | None = None,
                 cwd: str | Path | None = None, stdin: Stdio = None, stdout: Stdio = None,
                 stderr: Stdio = None) -> Forked | subprocess.Popen[bytes]:
    """``subprocess.Popen([python, "-m", module, *args], ...)`` (a protocol peer), forked from the fork
    server where that is the same: the child runs the module as ``__main__`` (``runpy.run_module``),
    with ``python -m``'s ``sys.argv`` and ``sys.path[0]`` (the working directory), without paying
    numpy's and the drivers' imports again (~0.9 s of CPU a peer exec'd)."""
    return _popen([sys.executable, "-m", module, *args], env, cwd, stdin, stdout, stderr)


def _popen(argv: list[str], env: Mapping[str, str] | None, cwd: str | Path | None, stdin: Stdio, stdout: Stdio,
           stderr: Stdio) -> Forked | subprocess.Popen[bytes]:
    full_env = dict(os.environ if env is None else env)
    server = fork_server()
    if server is None or not server.can_fork(full_env):
        return subprocess.Popen(argv, env=full_env, cwd=cwd, stdin=stdin, stdout=stdout, stderr=stderr)
    opened: list[int] = []
    try:
        out = _fd(stdout, 1, opened)
        err = out if stderr == subprocess.STDOUT else _fd(stderr, 2, opened)
        fds = [_fd(stdin, 0, opened), out, err]
        return server.spawn(argv, full_env, str(cwd if cwd is not None else os.getcwd()), fds)
    finally:
        for fd in opened:
            os.close(fd)


def _text(data: bytes) -> str:
    """As ``text=True`` reads a pipe: decoded, universal newlines."""
    return data.decode().replace("\r\n", "\n").replace("\r", "\n")


def run_cellctl(*args: str, env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                timeout: float | None = None, check: bool = False) -> subprocess.CompletedProcess[str]:
    """``subprocess.run([cellctl, *args], capture_output=True, text=True, ...)`` through :func:`popen_cellctl`."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = popen_cellctl(args, env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=out, stderr=err)
        try:
            code = proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
        out.seek(0)
        err.seek(0)
        done = subprocess.CompletedProcess([CELLCTL, *args], code, _text(out.read()), _text(err.read()))
    if check:
        done.check_returncode()
    return done
