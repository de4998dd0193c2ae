"""Fixtures shared by the whole suite: repo paths, free ports, a served cellctl process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
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
