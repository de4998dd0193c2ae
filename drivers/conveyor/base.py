"""The contract of a conveyor adapter: the encoder's count now, the belt's set speed, the pick window.

A conveyor is read, never moved, by cellctl: what moves is the belt (the plant's) and the robot that
tracks it. The count a picture was taken at travels with the frame (``Frame.meta["encoder_ticks"]``,
latched by the camera's trigger); ``ticks()`` is the count now, for faults (an encoder that stopped
while the belt moves) and for planning (where a queued part is now).
"""

from __future__ import annotations

import abc
from typing import Any

from drivers.base import DeviceBase


class ConveyorBase(DeviceBase):
    """Base of conveyor adapters (``cls(conveyor_id, settings)``)."""

    def __init__(self, conveyor_id: str) -> None:
        self.conveyor_id = conveyor_id

    def _open_device(self) -> None:
        self.open()

    @abc.abstractmethod
    def open(self) -> None:
        """Connect to the encoder (and the belt's drive, when it is readable)."""

    @abc.abstractmethod
    def ticks(self) -> int:
        """The encoder's count now. Called from more than one thread (a production run reads it on its own
        thread and on its count watcher's, every 50 ms): an adapter must be safe to call concurrently."""

    @abc.abstractmethod
    def speed_mm_s(self) -> float | None:
        """The belt's speed now as its drive reports it, mm/s (None: not known)."""

    @property
    @abc.abstractmethod
    def pick_window_mm(self) -> tuple[float, float]:
        """Base-frame x the robot can reach on the belt, mm (a recipe's window by default)."""

    def settings(self) -> dict[str, Any]:
        return {}
