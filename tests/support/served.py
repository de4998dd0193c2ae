"""``cellctl serve`` as a child process on a free loopback port: start it, reach it, stop it.

For what drives a whole service from outside: the end-to-end tests and the benchmarks (test
support, not part of the installed product). Only 127.0.0.1 is used.
"""

from __future__ import annotations

import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from tests.support.forked import CELLCTL, Forked, popen_cellctl
from tests.support.ports import free_port

__all__ = ["CELLCTL", "Reachable", "Served", "free_port", "run_job", "start_served", "stop_served"]


@dataclass
class Reachable:
    """A service on loopback: its base URL, engineer token and data dir, and a client for it."""

    base_url: str
    token: str
    data_dir: Path

    def client(self, token: str | None = None, timeout_s: float = 20.0) -> httpx.Client:
        headers = {"Authorization": f"Bearer {token or self.token}"}
        return httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout_s)


@dataclass
class Served(Reachable):
    """A ``cellctl serve`` process on loopback, with its base URL and engineer token: a fork of this
    test process's fork server (``tests/support/forked.py``), or an exec'd ``cellctl`` where the
    environment asks for one."""

    process: Forked | subprocess.Popen[bytes]


def start_served(tmp: Path, config: Path | None = None, extra_env: dict[str, str] | None = None,
                 token: str | None = None, timeout_s: float = 60.0, ready: bool = True) -> Served:
    """Start ``cellctl serve`` on a free port and wait until /health answers, and with ``ready``
    until it no longer says ``starting`` (its warm-up is done: what a user waits for)."""
    port = free_port()
    env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp / "data"), **(extra_env or {})}
    cmd = ["serve", "--host", "127.0.0.1", "--port", str(port)]
    if config is not None:
        cmd += ["--config", str(config)]
    with (tmp / "serve.log").open("wb") as log:
        proc = popen_cellctl(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"cellctl serve exited: {(tmp / 'serve.log').read_text()}")
        try:
            health = httpx.get(base + "/health", timeout=2.0)
            if health.status_code == 200 and not (ready and health.json().get("status") == "starting"):
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    else:
        proc.kill()
        raise RuntimeError(f"cellctl serve did not start: {(tmp / 'serve.log').read_text()}")
    if token is None:
        token_files = list((tmp / "data").glob("*.session-token"))
        if not token_files:  # what answered is not ours (free_port reserves ports so it cannot be)
            proc.kill()
            raise RuntimeError(f"{base} answers, but not as the service started in {tmp}: no session token")
        token = token_files[0].read_text().strip()
    return Served(base, token, tmp / "data", proc)


def stop_served(served: Served) -> None:
    served.process.terminate()
    try:
        served.process.wait(timeout=15)
    except subprocess.TimeoutExpired:
        served.process.kill()
        served.process.wait()


def run_job(http: httpx.Client, name: str, params: dict[str, Any], timeout_s: float = 240.0) -> dict[str, Any]:
    """Start routine ``name`` and wait until its job has ended; the job as JSON."""
    r = http.post(f"/routines/{name}", json=params)
    if r.status_code != 202:
        raise RuntimeError(f"routine {name} did not start: {r.status_code} {r.text}")
    job_id = r.json()["id"]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = http.get(f"/jobs/{job_id}").json()
        if job["state"] != "running":
            return dict(job)
        time.sleep(0.3)
    raise TimeoutError(f"{name} did not finish in {timeout_s} s")
