"""A run's cycle records: numbered, made JSON-safe, written in order by the run's writer thread.

A failed cycle's frame (``frames.KEPT_RESULTS``) is taken from the frame cache when the record is
made (the cache may drop it before the writer gets to it) and kept on disk with the record.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from cellctl.production.frames import KEPT_RESULTS, FailureFrames
from cellctl.production.records import Durations, clean, seen_fields
from cellctl.production.writer import Writer
from cellctl.services import Services
from cellctl.store import Store

log = logging.getLogger(__name__)


class CycleLog:
    """The cycle records of one run (``record``); ``n`` records made so far, ``last`` the last one (what a
    PLC reads as the last cycle's result)."""

    def __init__(self, services: Services, store: Store, writer: Writer, run_id: int, recipe_id: int,
                 recipe_version: int, failure_frames: FailureFrames | None) -> None:
        self.services, self.store, self.writer = services, store, writer
        self.run_id, self.recipe_id, self.recipe_version = run_id, recipe_id, recipe_version
        self.failure_frames = failure_frames
        self.n = 0
        self.last: dict[str, Any] | None = None

    def record(self, result: str, cand: Any = None, picture: Any = None, slot: int | None = None,
               T_place: np.ndarray | None = None, d: Durations | None = None, detail: str = "",
               t_cycle: float | None = None, durations: dict[str, float] | None = None,
               resolves: int | None = None, **extra: Any) -> dict[str, Any]:
        """Record cycle ``n + 1``; ``resolves``: the claimed slot its row confirms (one transaction)."""
        self.n += 1
        if durations is None and d is not None and t_cycle is not None:
            durations = d.as_ms(time.monotonic() - t_cycle)
        rec: dict[str, Any] = {
            "n": self.n, "t": time.time(), "run_id": self.run_id, "result": result, "slot": slot,
            "recipe_id": self.recipe_id, "recipe_version": self.recipe_version,
            **seen_fields(cand, picture, T_place), "durations_ms": durations, "detail": detail, **extra,
        }
        kept = None
        if result in KEPT_RESULTS and picture is not None and picture.frame_id is not None \
                and self.failure_frames is not None:
            try:  # taken now: the frame cache may drop it before the writer gets to it
                kept = self.services.frames.get(int(picture.frame_id))
            except KeyError:
                log.warning("production run %s: the frame of cycle %s left the cache before it was kept",
                            self.run_id, self.n)
        rec["frame_kept"] = kept is not None
        record = clean(rec)
        self.last = record
        run_id, n, frames, recipe_id = self.run_id, self.n, self.failure_frames, self.recipe_id

        def write() -> None:
            out = record
            if kept is not None and frames is not None and not frames.keep(run_id, n, kept, record):
                out = {**record, "frame_kept": False}
            self.store.add_cycle(run_id, out, None if resolves is None else (recipe_id, resolves))

        self.writer.put(write)
        return record
