"""What the service's front ends (REST, Modbus, OPC UA) share: config, live cell, store, jobs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cellctl.cell import Cell
from cellctl.config import CellConfig
from cellctl.jobs import JobManager
from cellctl.pick.frames import FrameCache


@dataclass
class Services:
    """The running cell: one per service process."""

    config: CellConfig
    cell: Cell
    store: Any
    """``cellctl.store.Store`` (SQLite or PostgreSQL)."""
    jobs: JobManager
    frames: FrameCache = field(default_factory=FrameCache)

    def close(self) -> None:
        self.jobs.shutdown()
        self.cell.close()
        close = getattr(self.store, "close", None)
        if close is not None:
            close()
