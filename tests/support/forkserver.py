"""The fork server: one pre-imported Python per test process that forks ``cellctl`` runs.

Run as ``python -m tests.support.forkserver SOCKET`` by ``tests/support/forked.py`` (its client,
which the suite uses; read that module first). It imports what ``cellctl serve`` and the other
commands import (about 3 s of CPU a fresh ``cellctl`` pays), then answers on a Unix socket: each
request (argv, environment, working directory, and three descriptors for stdin, stdout, stderr) is
forked into a child that takes those descriptors, that environment and that directory and runs the
``cellctl`` console script (or, for ``[python, "-m", MODULE, ...]``, that module: the protocol peers of
``tests/drivers/peers.py``) as a fresh process would (``runpy``: the script's ``sys.exit(main())``,
its ``__main__``, the interpreter's own exit with its atexit handlers and thread joins). The child is
a real process with its own pid: signals, ``kill -9``, exit codes and log files work on it as on an
exec'd ``cellctl``. The server answers each request with the child's pid and a pidfd, and when the
child ends, with its wait status and its CPU seconds (user + system) on the same connection.

The server is single-threaded and forks from its one thread: the thread pools that numpy's and
scipy's OpenBLAS and OpenCV start at import are shut down by their own fork handlers, and each fork
checks that ``/proc/self/task`` holds this thread alone. It ends when its client's pipe (its stdin)
closes; children still running are left to run, as an exec'd child outlives a dead parent.

Nothing is imported here at module level beyond the standard library: a ``spawn`` child of a forked
``cellctl`` (the warm-up's process pool, the UR control worker) re-runs the console script as its
``__main__``, not this module, as the exec'd ``cellctl`` does.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import json
import os
import select
import signal
import socket
import struct
import sys
from dataclasses import dataclass

PRELOAD = (
    # what `cellctl serve` imports (python -X importtime on a served virtual cell), and every command's module
    "cellctl.cli", "uvicorn", "cellctl.api.app", "cellctl.plc", "cellctl.store.startup",
    "scipy.interpolate", "scipy.spatial", "sqlalchemy.dialects.sqlite", "numba.typed", "drivers.sim",
    "calibration.synthetic", "python_multipart", "anyio.streams.memory", "anyio.streams.stapled",
    "anyio._core._fileio", "uvicorn.loops.auto", "uvicorn.protocols.http.auto", "uvicorn.lifespan.on",
    "email_validator", "cffi",
)
"""Modules imported once, before any fork (a module that fails to import is left to the child)."""
HEADER = struct.Struct("!I")
"""A request: its JSON's length, then the JSON; three descriptors ride with the first bytes."""


@dataclass
class Request:
    """One ``cellctl`` run: the console script's path and arguments, environment, directory, stdio."""

    argv: list[str]
    env: dict[str, str]
    cwd: str
    fds: list[int]


def preload() -> None:
    import cellctl.cli

    for name in PRELOAD + tuple(f"cellctl.cli.{m}" for m in cellctl.cli.COMMAND_MODULES):
        with contextlib.suppress(ImportError):
            importlib.import_module(name)


def load_compiled_loops() -> None:
    """Load the renderer's, matcher's and calibration solver's compiled loops from numba's cache (what
    every served cell's warm-up does first, ~1 s of CPU), on this thread alone: the renderer's pool
    is held at one thread meanwhile, so no pool thread exists to be lost by a fork. The matcher's
    warm-up search is left to each child's own warm-up (``vision.shape.warm_up`` still runs it there)."""
    from cellctl import warmup
    from drivers.sim.imaging import renderer
    from vision.shape.warmup import load_kernels

    threads_were = renderer.RENDER_THREADS
    renderer.RENDER_THREADS = 1
    try:
        warmup.warm_renderer()
    finally:
        renderer.RENDER_THREADS = threads_were
    load_kernels()
    warmup.warm_calibration()


def threads() -> int:
    return len(os.listdir("/proc/self/task"))


def shut_pools() -> None:
    """One fork that exits at once: OpenBLAS's and OpenCV's fork handlers join the thread pools they
    started at import, so the server is single-threaded from now on (``threads()`` checks it)."""
    pid = os.fork()
    if pid == 0:
        os._exit(0)
    os.waitpid(pid, 0)


def _read_request(conn: socket.socket) -> Request:
    data, fds, _flags, _addr = socket.recv_fds(conn, 1 << 16, 3)
    if len(data) < HEADER.size or len(fds) != 3:
        raise ValueError("a request is a length, its JSON and three descriptors")
    (size,) = HEADER.unpack_from(data)
    body = data[HEADER.size:]
    while len(body) < size:
        more = conn.recv(size - len(body))
        if not more:
            raise ValueError("the request ended early")
        body += more
    msg = json.loads(body)
    return Request(list(msg["argv"]), dict(msg["env"]), str(msg["cwd"]), fds)


def serve(path: str) -> Request:
    """Answer requests until the client's pipe closes (then exit); returns only in a forked child."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(64)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)
    children: dict[int, socket.socket] = {}
    os.write(1, b"ready\n")
    while True:
        readable, _, _ = select.select([listener.fileno(), 0, wake_r], [], [])
        if 0 in readable and not os.read(0, 4096):
            os._exit(0)  # the client is gone: so is its fork server (running children go on)
        if wake_r in readable:
            os.read(wake_r, 4096)
        if listener.fileno() in readable:
            conn, _ = listener.accept()
            try:
                request = _read_request(conn)
            except (OSError, ValueError) as exc:
                conn.close()
                print(f"forkserver: bad request: {exc}", file=sys.stderr, flush=True)
                continue
            if threads() != 1:
                print(f"forkserver: {threads()} threads before a fork", file=sys.stderr, flush=True)
            pid = os.fork()
            if pid == 0:  # the child: nothing of the server's stays open or installed
                signal.set_wakeup_fd(-1)
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                for sock in (listener, conn, *children.values()):
                    sock.close()
                os.close(wake_r)
                os.close(wake_w)
                return request
            for fd in request.fds:
                os.close(fd)
            pidfd = os.pidfd_open(pid)
            try:
                socket.send_fds(conn, [f"{pid}\n".encode()], [pidfd])
                children[pid] = conn
            except OSError:
                conn.close()
            finally:
                os.close(pidfd)
        _reap(children)


def _reap(children: dict[int, socket.socket]) -> None:
    while True:
        try:
            pid, status, usage = os.wait4(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        conn = children.pop(pid, None)
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.sendall(f"{status} {usage.ru_utime + usage.ru_stime}\n".encode())
            conn.close()


def become(request: Request) -> None:
    """Take the request's stdio, directory, environment and argv, as an exec'd process has them."""
    for target, fd in enumerate(request.fds):
        os.dup2(fd, target)
    for fd in request.fds:
        if fd > 2:
            os.close(fd)
    os.chdir(request.cwd)
    os.environ.clear()
    os.environ.update(request.env)
    sys.argv = list(request.argv)
    sys.path[0] = os.path.dirname(request.argv[0])  # a console script's sys.path[0], not this server's
    if "numpy" in sys.modules:  # a fresh process seeds numpy's global generator from the OS (random reseeds itself)
        sys.modules["numpy"].random.seed()


def main() -> None:
    preload()
    load_compiled_loops()
    gc.collect()
    gc.freeze()  # the imported objects stay out of the children's collections: their pages stay shared
    shut_pools()
    if threads() != 1:
        print(f"forkserver: {threads()} threads after start-up", file=sys.stderr, flush=True)
    sys.stdout.flush()
    with open(sys.argv[1] + ".env.json", "w") as f:  # what a client compares a run's environment with
        json.dump(dict(os.environ), f)
    request = serve(sys.argv[1])
    become(request)
    import runpy

    if request.argv[1:2] == ["-m"] and len(request.argv) > 2:  # `python -m MODULE ARGS`: a protocol peer
        sys.argv = request.argv[2:]
        sys.path[0] = request.cwd  # as `python -m` has it
        runpy.run_module(request.argv[2], run_name="__main__", alter_sys=True)
    else:
        runpy.run_path(request.argv[0], run_name="__main__")


if __name__ == "__main__":
    main()
