"""What the service's front ends (REST, Modbus, OPC UA) share: config, live cell, store, jobs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cellctl.cell import Cell
from cellctl.config import CellConfig
from cellctl.jobs import JobManager
from cellctl.pick.frames import FrameCache

if TYPE_CHECKING:
    from cellctl.latches import LatchKeeper


@dataclass
class Services:
    """The running cell: one per service process."""

    config: CellConfig
    cell: Cell
    store: Any
    """``cellctl.store.Store`` (SQLite or PostgreSQL)."""
    jobs: JobManager
    frames: FrameCache = field(default_factory=FrameCache)
    latches: LatchKeeper | None = None
    """Stores every change of a robot's Stop latch (None: the latches live in memory only)."""

    def close(self) -> None:
        self.jobs.shutdown()
        self.cell.close()
        if self.latches is not None:
            self.latches.close()
        close = getattr(self.store, "close", None)
        if close is not None:
            close()
