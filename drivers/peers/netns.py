"""A loopback-only network namespace to run GigE Vision clients in, and the fake GigE camera peer.

Aravis discovery broadcasts on every network interface, so no GigE client may run in the
machine's own namespace. :func:`run_in_loopback_namespace` re-executes a script under
``unshare -n`` (as root; ``unshare -rn`` otherwise); the script calls :func:`enter_loopback_only`
first, which checks that ``lo`` is its only interface (and refuses to run otherwise) and brings
it up. :class:`FakeCamera` runs ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (a real GVCP/GVSP peer)
inside it. The script prints one JSON object on its last stdout line: that is the result.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
FAKE_CAMERA = "arv-fake-gv-camera-0.8"


def run_in_loopback_namespace(script: Path, *args: str, timeout_s: float = 90.0) -> dict[str, Any]:
    """Run ``python script args`` in a fresh network namespace and return its JSON result."""
    unshare = ["unshare", "-n"] if os.geteuid() == 0 else ["unshare", "-rn"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [*unshare, sys.executable, str(script), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(
            f"netns run of {script.name} {' '.join(args)} failed (exit {proc.returncode}):\n"
            f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        )
    result: dict[str, Any] = json.loads(lines[-1])
    return result


def enter_loopback_only() -> None:
    """Inside the namespace: refuse to run unless ``lo`` is the only interface; bring it up."""
    names = [n for _, n in socket.if_nameindex()]
    if names != ["lo"]:
        raise SystemExit(f"refusing to run: this network namespace has interfaces {names}, not only lo")
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)


class FakeCamera:
    """``arv-fake-gv-camera-0.8`` on 127.0.0.1, stopped by its pid."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> FakeCamera:
        self.proc = subprocess.Popen(
            [FAKE_CAMERA, "-i", "127.0.0.1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        time.sleep(0.5)
        return self

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=5)
        self.proc = None
