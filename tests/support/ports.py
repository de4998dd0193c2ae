"""Loopback TCP ports for the test peers and served processes, never handed out twice at once.

``bind(("127.0.0.1", 0))`` returns a port from the kernel's ephemeral range, and between closing that
socket and the server binding the port, the kernel may give the same port to another test worker's
``bind(0)`` or to any outgoing connection (they draw from the same range). Under xdist with served
processes that happened: a test reached another worker's service on "its" port and found no token.

So ports come from below the ephemeral range (``/proc/sys/net/ipv4/ip_local_port_range``), and each is
reserved across processes by creating a marker file (``O_EXCL``) that expires after
``RESERVATION_S``: two workers, or two pytest runs side by side, never get the same port while a
test may still be starting its server on it.
"""

from __future__ import annotations

import os
import random
import socket
import tempfile
import time
from pathlib import Path

LOW_PORT = 20000
RESERVATION_S = 600.0
RESERVATIONS = Path(tempfile.gettempdir()) / "cellctl-test-ports"


def _ephemeral_low() -> int:
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return max(low, LOW_PORT + 1000)


def _reserve(port: int) -> bool:
    marker = RESERVATIONS / str(port)
    if _reserve_once(marker):
        return True
    try:
        if time.time() - marker.stat().st_mtime < RESERVATION_S:
            return False
        marker.unlink()  # an old reservation: its test is long over
    except FileNotFoundError:
        pass
    return _reserve_once(marker)


def _reserve_once(marker: Path) -> bool:
    try:
        os.close(os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        return True
    except FileExistsError:
        return False


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now and reserved for this caller for ``RESERVATION_S``."""
    RESERVATIONS.mkdir(mode=0o700, exist_ok=True)
    high = _ephemeral_low()
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(2000):
        port = rng.randrange(LOW_PORT, high)
        if _reserve(port) and _bindable(port):
            return port
    raise RuntimeError(f"no free loopback port in {LOW_PORT}-{high - 1} (reservations in {RESERVATIONS})")
