"""Fixtures that start and stop the real protocol peers of the driver tests (all on 127.0.0.1)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.drivers.peers import PeerProcess


@pytest.fixture
def ur_ports() -> Iterator[None]:
    """Exclusive use of the fixed UR ports on 127.0.0.1 (ur_rtde cannot use others)."""
    from drivers.peers.ur_emulator import fixed_port_lock

    with fixed_port_lock():
        yield


@pytest.fixture
def ur_emulator(ur_ports: None) -> Iterator[PeerProcess]:
    peer = PeerProcess("drivers.peers.ur_emulator", ready_port=30003).start()
    try:
        yield peer
    finally:
        peer.stop()
