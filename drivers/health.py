"""What a device says about itself: ``health()`` returns a ``DeviceHealth``, never a free dict.

Every adapter has ``health()`` (the ``Monitored`` Protocol); the service's metrics and status
pages read these fields. Counters are since the adapter was built; times in seconds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Protocol, runtime_checkable


@dataclass(frozen=True)
class DeviceHealth:
    """A device's availability and its outage counters."""

    available: bool
    reason: str = ""
    """Why it is not available (empty when it is): what failed and what the adapter does about it."""
    outages: int = 0
    """Times the device was lost after it had worked."""
    reconnects: int = 0
    """Reconnect attempts the adapter made by itself."""
    last_outage_s: float | None = None
    """Duration of the last outage that ended (s); None when the adapter does not measure it."""
    state_age_s: float | None = None
    """Age of the newest robot state (s), for adapters that stream state."""
    frames_received: int | None = None
    """Camera frames received complete."""
    frames_incomplete: int | None = None
    frames_lost: int | None = None
    """Camera frames the device sent that never arrived (stream gaps)."""

    def as_dict(self) -> dict[str, Any]:
        """The fields that apply to this device (None ones left out), for JSON."""
        return {k: v for k, v in asdict(self).items() if v is not None}


@runtime_checkable
class Monitored(Protocol):
    """A device that reports its health."""

    def health(self) -> DeviceHealth: ...
