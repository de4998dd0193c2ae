"""Pacing a front end's protocol work so that no polling client can take the interpreter from Stop.

Every front end parses its clients' frames in Python, on its own event loop, under the one
interpreter lock the REST service (and so ``POST /robots/{id}/stop``) also needs. A client polling
as fast as it is answered would keep that lock busy: measured with every front end polled at its
fastest and no pacing, Stop took up to 0.76 s (bench/plc.py). A :class:`Pacer` is a budget of work
time: it holds ``burst_s`` seconds of work and refills at ``share`` seconds per second; a frame that
finds it spent waits (``asyncio.sleep``: the loop and the lock are free meanwhile) until it is
refilled. A handshake's few frames fit in the burst; only a client that keeps the front end busy is
slowed.

Two budgets hold each frame: the front end's own (:func:`front_end_pacer`, ``SHARE`` of the
interpreter for all its connections) and the one every front end of the process shares
(:data:`ALL_FRONT_ENDS`, ``SHARED_SHARE``). Each front end alone was within Stop's 100 ms; four
polled at once took 4 x 20 % plus OPC UA's unpaced work, more than the interpreter has, and Stop
then waited behind them (p95 110 ms, bench/plc.py, 2026-12-05). The shared budget keeps half of the
interpreter for everything else (REST, Stop, the pick) whatever the number of busy front ends.

The work is charged by ``clock``: wall time (``time.perf_counter``) where the paced section has no
``await`` inside (Modbus, EtherNet/IP, the robot socket: parsing and answering), the loop thread's
CPU time (``time.thread_time``) where it has (OPC UA: a method call awaits the pick, which is not the
front end's work).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from typing import Any

SHARE = 0.2
"""The largest fraction of wall time one front end spends on its clients' frames when they keep it busy."""
SHARED_SHARE = 0.5
"""The largest fraction of wall time all the front ends together spend on their clients' frames."""
BURST_S = 0.15
"""Work time a front end may spend at once before the pacing starts."""


class Budget:
    """Work time that refills at ``share`` seconds per second up to ``burst_s`` (thread-safe)."""

    def __init__(self, share: float, burst_s: float) -> None:
        self.share, self.burst_s = share, burst_s
        self._credit = burst_s
        self._at = time.perf_counter()
        self._lock = threading.Lock()

    def owed_s(self) -> float:
        """How long to wait until the budget is no longer overspent (0: go ahead)."""
        with self._lock:
            self._refill()
            return max(0.0, -self._credit / self.share)

    def charge(self, spent_s: float) -> None:
        with self._lock:
            self._refill()
            self._credit -= spent_s

    def _refill(self) -> None:
        now = time.perf_counter()
        self._credit = min(self.burst_s, self._credit + (now - self._at) * self.share)
        self._at = now


ALL_FRONT_ENDS = Budget(SHARED_SHARE, BURST_S)
"""The budget every front end of this process shares (one interpreter lock per process)."""


class Pacer:
    """``t0 = await pacer.wait()`` before a frame's work and ``pacer.done(t0)`` after it (one event loop)."""

    def __init__(self, share: float = SHARE, burst_s: float = BURST_S, shared: Budget | None = ALL_FRONT_ENDS,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.share, self.burst_s = share, burst_s
        self.own = Budget(share, burst_s)
        self.shared = shared
        self.clock = clock
        self.waited_s = 0.0
        """Time this front end's frames waited for the budgets (``GET /plc/status``: ``paced.waited_s``)."""
        self.frames = 0
        """Frames (messages) done under this pacer."""

    def status(self) -> dict[str, Any]:
        return {"frames": self.frames, "waited_s": round(self.waited_s, 3)}

    async def wait(self) -> float:
        """Wait until both budgets allow more work; returns ``clock()`` for :meth:`done`."""
        while True:
            delay = max(self.own.owed_s(), self.shared.owed_s() if self.shared is not None else 0.0)
            if delay <= 0:
                return self.clock()
            self.waited_s += delay
            await asyncio.sleep(delay)

    def done(self, t0: float) -> None:
        spent = max(0.0, self.clock() - t0)
        self.frames += 1
        self.own.charge(spent)
        if self.shared is not None:
            self.shared.charge(spent)
