"""Bases of camera and digital I/O adapters, and the plumbing every adapter shares (``DeviceBase``:
``with`` opens, ``close()`` is idempotent, ``health()``). The robot's base is ``drivers.robot_base``.
"""

from __future__ import annotations

import abc
from types import TracebackType
from typing import Any, Self

from drivers.errors import DeviceInitError
from drivers.health import DeviceHealth
from drivers.values import Frame


class DeviceBase(abc.ABC):
    """Context-manager plumbing shared by adapters: ``with`` opens, ``close()`` is idempotent."""

    def health(self) -> DeviceHealth:
        """The device's availability and outage counters; adapters that count outages override it."""
        return DeviceHealth(available=True)

    def __enter__(self) -> Self:
        self._open_device()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    @abc.abstractmethod
    def _open_device(self) -> None:
        """Open or connect the underlying device."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""


class CameraBase(DeviceBase):
    """Base of camera adapters; ``with cam:`` opens it."""

    def __init__(self, camera_id: str) -> None:
        self.camera_id = camera_id

    def _open_device(self) -> None:
        self.open()

    @abc.abstractmethod
    def open(self) -> None:
        """Open the camera and start acquisition."""

    @abc.abstractmethod
    def grab(self, timeout_s: float = 2.0) -> Frame:
        """Return the newest complete frame; DeviceTimeout when none arrives in time."""

    def set_exposure_us(self, exposure_us: float) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: exposure cannot be set on this camera")

    def set_gain_db(self, gain_db: float) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: gain cannot be set on this camera")

    def set_trigger(self, mode: str) -> None:
        raise DeviceInitError(f"camera {self.camera_id}: trigger mode cannot be set on this camera")

    def settings(self) -> dict[str, Any]:
        return {}

    def control_ranges(self) -> dict[str, Any]:
        """The controls this camera offers and their bounds: ``{"exposure_us": [lo, hi], "gain_db": [lo, hi],
        "trigger": [modes...]}``, a key only for a control it has (none here: a driver that sets one says so)."""
        return {}


class DigitalIOBase(DeviceBase):
    """Base of digital IO adapters."""

    def __init__(self, io_id: str) -> None:
        self.io_id = io_id

    def _open_device(self) -> None:
        self.open()

    @abc.abstractmethod
    def open(self) -> None:
        """Open the IO device."""

    @abc.abstractmethod
    def read_input(self, channel: int) -> bool:
        """Read one digital input."""

    @abc.abstractmethod
    def write_output(self, channel: int, value: bool) -> None:
        """Set one digital output."""
