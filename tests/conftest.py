"""Fixtures shared by the whole suite: repo paths, test data, free ports, a served cellctl process.

It also marks every test by what it needs (``pytest -m "not slow"`` is the fast loop; see
docs/testing.md): ``unit`` (in-process, no peer), ``peer`` (a protocol peer on loopback: an
emulator, a fake camera, socat, PostgreSQL), ``e2e`` (a served ``cellctl`` process), ``browser``
(headless Chromium), and ``slow`` (over about 3 s on the 2-core reference machine: the measured
list in ``tests/slow.txt``, plus every browser test).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
"""Real images and measurements copied into the repository, each folder with SOURCE.txt and LICENSE.txt."""
CELLCTL = str(Path(sys.executable).with_name("cellctl"))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Served:
    """A ``cellctl serve`` process on loopback, with its base URL and engineer token."""

    process: subprocess.Popen[bytes]
    base_url: str
    token: str
    data_dir: Path

    def client(self, token: str | None = None, timeout_s: float = 20.0) -> httpx.Client:
        headers = {"Authorization": f"Bearer {token or self.token}"}
        return httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout_s)


def start_served(tmp: Path, config: Path | None = None, extra_env: dict[str, str] | None = None,
                 token: str | None = None, timeout_s: float = 60.0) -> Served:
    """Start ``cellctl serve`` on a free port and wait until /health answers."""
    port = free_port()
    env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp / "data"), **(extra_env or {})}
    cmd = [CELLCTL, "serve", "--host", "127.0.0.1", "--port", str(port)]
    if config is not None:
        cmd += ["--config", str(config)]
    log = (tmp / "serve.log").open("wb")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"cellctl serve exited: {(tmp / 'serve.log').read_text()}")
        try:
            if httpx.get(base + "/health", timeout=2.0).status_code == 200:
                break
        except httpx.HTTPError:
            time.sleep(0.2)
    else:
        proc.kill()
        raise RuntimeError(f"cellctl serve did not start: {(tmp / 'serve.log').read_text()}")
    if token is None:
        token_files = list((tmp / "data").glob("*.session-token"))
        token = token_files[0].read_text().strip() if token_files else ""
    return Served(proc, base, token, tmp / "data")


def stop_served(served: Served) -> None:
    served.process.terminate()
    try:
        served.process.wait(timeout=15)
    except subprocess.TimeoutExpired:
        served.process.kill()
        served.process.wait()


@pytest.fixture(scope="session")
def served_virtual_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """One ``cellctl serve`` of the built-in virtual cell for the session's read-only tests."""
    served = start_served(tmp_path_factory.mktemp("serve"))
    try:
        yield served
    finally:
        stop_served(served)


# -- markers ----------------------------------------------------------------------------------------

SLOW_LIST = Path(__file__).with_name("slow.txt")
E2E_HINTS = ("start_served(", "served_virtual_cell", "start_plc_cell(", "plc_cell", "uvicorn")
PEER_HINTS = ("PeerProcess", "netns", "postgres", "socat", "arv-fake", "ur_emulator", "Aravis")
_module_text: dict[Path, str] = {}


def slow_tests(lines: Iterable[str]) -> set[str]:
    """Node ids of ``tests/slow.txt`` (one per line; ``#`` starts a comment)."""
    return {ln.split("#", 1)[0].strip() for ln in lines} - {""}


def kinds_of(rel_path: str, fixturenames: Iterable[str], module_text: str) -> set[str]:
    """The kind markers of a test from its path (relative to tests/), its fixtures and its module."""
    fixtures = set(fixturenames)
    if rel_path.startswith("ui/"):
        return {"browser", "e2e"}
    kinds = set()
    if rel_path == "test_readme.py" or any(h in module_text for h in E2E_HINTS) \
            or any(f.startswith(("served", "plc_cell")) for f in fixtures):
        kinds.add("e2e")
    if any(h in module_text for h in PEER_HINTS) or fixtures & {"ur_emulator", "postgres", "postgres_url"}:
        kinds.add("peer")
    return kinds or {"unit"}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow = slow_tests(SLOW_LIST.read_text().splitlines()) if SLOW_LIST.exists() else set()
    root = Path(__file__).parent
    for item in items:
        path = Path(str(item.path))
        if path not in _module_text:
            _module_text[path] = path.read_text() if path.suffix == ".py" else ""
        rel = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        kinds = kinds_of(rel, getattr(item, "fixturenames", ()), _module_text[path])
        for kind in sorted(kinds):
            item.add_marker(kind)
        base_id, file_id = item.nodeid.split("[", 1)[0], item.nodeid.split("::", 1)[0]
        if "browser" in kinds or {item.nodeid, base_id, file_id} & slow:
            item.add_marker("slow")
