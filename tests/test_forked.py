"""The fork server the suite runs ``cellctl`` through (tests/support/forked.py): its children are
processes as an exec'd ``cellctl`` is, and nothing it imports once has read what a child changes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.support.forked import READ_AT_USE, REPO, Forked, fork_server, popen_cellctl, popen_module, run_cellctl
from tests.support.forkserver import PRELOAD
from tests.support.ports import free_port
from tests.support.wait import wait_until

RECORD_READS = """
import json, os, sys
reads = []
class Recording(type(os.environ)):
    def __getitem__(self, key):
        frame = sys._getframe(1)
        if frame.f_code.co_name != "__iter__":  # a copy of the whole environment is not a read of one variable
            while frame.f_code.co_filename.startswith("<frozen") or frame.f_code.co_filename == os.__file__:
                frame = frame.f_back
            if not frame.f_code.co_filename.endswith("sysconfig.py"):  # Python's user base: fixed at start-up
                reads.append([key, f"{frame.f_code.co_filename}:{frame.f_lineno}"])
        return super().__getitem__(key)
os.environ = Recording(os.environ._data, os.environ.encodekey, os.environ.decodekey,
                       os.environ.encodevalue, os.environ.decodevalue)
from tests.support import forkserver
forkserver.preload()
print(json.dumps(reads))
"""


def test_nothing_the_fork_server_imports_reads_what_a_child_may_change() -> None:
    """The variables a forked run may set differently (``READ_AT_USE``) are read when used, never at
    import: else the server's value would be frozen into every child."""
    r = subprocess.run([sys.executable, "-c", RECORD_READS], capture_output=True, text=True, cwd=REPO, timeout=120,
                       check=True)
    reads = [(k, where) for k, where in json.loads(r.stdout) if k.startswith(READ_AT_USE)]
    assert reads == [], f"read at import: {reads}"
    assert "cellctl.api.app" in PRELOAD and "uvicorn" in PRELOAD


def test_a_forked_run_has_its_own_env_cwd_stdio_and_exit_code(tmp_path: Path) -> None:
    env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp_path / "elsewhere")}
    r = run_cellctl("config", "default", env=env, cwd=tmp_path, check=True)
    assert r.stdout == (REPO / "deploy" / "examples" / "virtual-cell.yaml").read_text()
    bad = run_cellctl("no-such-command")
    assert bad.returncode == 2 and "invalid choice" in bad.stderr and bad.stdout == ""


def test_a_forked_serve_is_a_process_of_its_own(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Its own pid, cwd and data dir (the environment it was given), /health on its port, and kill -9
    ends it as it ends an exec'd one (returncode -9); the server forked it from its only thread."""
    monkeypatch.setenv("CELLCTL_TEST_FORK", "1")  # this test is about the fork even in a run that execs
    port = free_port()
    env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp_path / "data")}
    with (tmp_path / "serve.log").open("wb") as log:
        proc = popen_cellctl(["serve", "--host", "127.0.0.1", "--port", str(port)], env=env, cwd=tmp_path,
                             stdout=log, stderr=subprocess.STDOUT)
    assert isinstance(proc, Forked) and proc.pid != os.getpid()
    try:
        wait_until(lambda: _answers(port), timeout_s=60, what="the forked serve's /health", poll_s=0.2)
        assert Path(f"/proc/{proc.pid}/cwd").resolve() == tmp_path.resolve()
        assert list((tmp_path / "data").glob("*.session-token"))  # the data dir of its environment
        assert proc.poll() is None
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=15) == -signal.SIGKILL
    finally:
        proc.kill()
    assert "cellctl: no tokens in the config" in (tmp_path / "serve.log").read_text()
    server = fork_server()
    assert server is not None
    assert " threads " not in Path(server.dir, "server.log").read_text()  # one thread at start-up and at each fork


def test_an_environment_read_at_import_is_exec_d() -> None:
    """``NUMBA_CACHE_DIR`` (numba reads it at import) cannot be a fork: the run is exec'd, same answer."""
    proc = popen_cellctl(["--version"], env={**os.environ, "NUMBA_CACHE_DIR": "/nonexistent"},
                         stdout=subprocess.DEVNULL)
    assert isinstance(proc, subprocess.Popen)
    assert proc.wait(timeout=60) == 0


def _answers(port: int) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/health", timeout=2.0).status_code == 200
    except httpx.HTTPError:
        return False


PROBE = """
import json, sys
print(json.dumps({"name": __name__, "argv": sys.argv, "path0": sys.path[0], "spec": __spec__.name}))
sys.exit(3)
"""


def test_a_forked_module_run_is_python_dash_m(tmp_path: Path) -> None:
    """A protocol peer (``python -m MODULE ARGS``, tests/drivers/peers.py) forked: ``__main__``, ``sys.argv``
    (the module's file first), ``sys.path[0]`` (the working directory) and the exit code as ``python -m``'s."""
    (tmp_path / "probe_peer.py").write_text(PROBE)
    with (tmp_path / "out").open("wb") as out:
        proc = popen_module("probe_peer", ["--port", "5"], cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=out)
        assert isinstance(proc, Forked) and proc.wait(60) == 3
    exec_d = subprocess.run([sys.executable, "-m", "probe_peer", "--port", "5"], cwd=tmp_path, capture_output=True,
                            text=True, timeout=60)
    assert exec_d.returncode == 3
    forked, expected = json.loads((tmp_path / "out").read_text()), json.loads(exec_d.stdout)
    assert forked == expected and forked["argv"] == [str(tmp_path / "probe_peer.py"), "--port", "5"], (forked, expected)
