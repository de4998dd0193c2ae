"""The composition root: what the service's front ends (REST, Modbus, OPC UA) share.

One ``Services`` per service process holds every piece of live state as a typed field: the config,
the live cell, the store, the jobs, the frame cache, the Stop latches' keeper, the metrics, the
calibration report cache, the production manager, the PLC request engine and the drift monitor (made
on first use). Nothing in ``cellctl`` keeps live state in a module-level registry; ``close`` ends it
all, in order.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cellctl.cell import Cell
from cellctl.config import CellConfig
from cellctl.jobs import JobManager
from cellctl.metrics import CellMetrics
from cellctl.pick.frames import FrameCache

if TYPE_CHECKING:
    from cellctl.drift.monitor import DriftMonitor
    from cellctl.latches import LatchKeeper
    from cellctl.plc.engine import Engine
    from cellctl.production.manager import ProductionManager
    from cellctl.store import Store


class ReportCache:
    """Built calibration report pages, keyed by (calibration id, sha256 of its record); the newest
    ``capacity`` are kept (a record is immutable, so a page never goes stale). Thread-safe."""

    def __init__(self, capacity: int = 32) -> None:
        self.capacity = capacity
        self._pages: OrderedDict[tuple[int, str], str] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[int, str]) -> str | None:
        with self._lock:
            return self._pages.get(key)

    def put(self, key: tuple[int, str], page: str) -> None:
        with self._lock:
            self._pages[key] = page
            while len(self._pages) > self.capacity:
                self._pages.popitem(last=False)


@dataclass
class Services:
    """The running cell: one per service process."""

    config: CellConfig
    cell: Cell
    store: Store
    """The store (``cellctl.store.Store``: SQLite or PostgreSQL)."""
    jobs: JobManager
    frames: FrameCache = field(default_factory=FrameCache)
    latches: LatchKeeper | None = None
    """Stores every change of a robot's Stop latch (None: the latches live in memory only)."""
    metrics: CellMetrics = field(default_factory=CellMetrics)
    """This service's Prometheus metrics (its own registry), fed by the picks, the jobs and the cell."""
    reports: ReportCache = field(default_factory=ReportCache)
    """Calibration report pages built so far (``GET /calibrations/{id}/report``)."""
    _production: ProductionManager | None = field(default=None, init=False, repr=False)
    _plc_engine: Engine | None = field(default=None, init=False, repr=False)
    _drift: DriftMonitor | None = field(default=None, init=False, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def __post_init__(self) -> None:
        self.metrics.attach(self.cell)
        self.jobs.metrics = self.metrics

    @property
    def production(self) -> ProductionManager:
        """The production runs of this service (the manager is made on first use)."""
        from cellctl.production.manager import ProductionManager

        with self._lock:
            if self._production is None:
                self._production = ProductionManager(self)
            return self._production

    @property
    def production_if_made(self) -> ProductionManager | None:
        """The production manager if one was made (no store access: safe on an event loop)."""
        with self._lock:
            return self._production

    @property
    def plc_engine(self) -> Engine:
        """The PLC request engine every PLC front end shares (``cellctl.plc.engine``; made on first use)."""
        from cellctl.plc.engine import Engine

        with self._lock:
            if self._plc_engine is None:
                self._plc_engine = Engine(self)
            return self._plc_engine

    @property
    def drift(self) -> DriftMonitor | None:
        """The drift monitor (``cellctl.drift``; made on first use); None when ``drift:`` is not configured."""
        if self.config.drift is None:
            return None
        from cellctl.drift.monitor import DriftMonitor

        with self._lock:
            if self._drift is None:
                self._drift = DriftMonitor(self, self.config.drift)
            return self._drift

    @property
    def drift_if_made(self) -> DriftMonitor | None:
        """The drift monitor if one was made (no store access: safe on an event loop)."""
        with self._lock:
            return self._drift

    def close_plc_engine(self) -> None:
        """Close the PLC request engine (after its front ends stopped): the next use makes a new one."""
        with self._lock:
            engine, self._plc_engine = self._plc_engine, None
        if engine is not None:
            engine.close()

    def stop_production(self, reason: str = "the service is shutting down") -> list[int]:
        """Stop this service's production runs now (``ProductionManager.shutdown``); the manager stays
        and refuses new starts (a PLC command arriving meanwhile). The ids of the runs it ended."""
        manager = self.production_if_made
        return [] if manager is None else manager.shutdown(reason)

    def close(self) -> None:
        """End everything this service runs: production runs (their robots halted, records written),
        jobs, the cell's devices, the latch writer, the store; the metrics stop reading the cell."""
        try:
            self.stop_production()
            drift = self.drift_if_made
            if drift is not None:
                drift.close()
            self.close_plc_engine()
            self.jobs.shutdown()
            self.cell.close()
            if self.latches is not None:
                self.latches.close()
            close = getattr(self.store, "close", None)
            if close is not None:
                close()
        finally:
            self.metrics.detach()
