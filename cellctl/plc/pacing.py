"""Pacing a front end's protocol work so that no polling client can take the interpreter from Stop.

Every front end parses its clients' frames in Python, on its own event loop, under the one
interpreter lock the REST service (and so ``POST /robots/{id}/stop``) also needs. A client polling
as fast as it is answered would keep that lock busy: measured with every front end polled at its
fastest and no pacing, Stop took up to 0.76 s (bench/plc.py). A :class:`Pacer` is a budget of work
time per front end (all its connections): it holds ``burst_s`` seconds of work and refills at
``share`` seconds per second; a frame that finds it spent waits (``asyncio.sleep``: the loop and the
lock are free meanwhile) until it is refilled. A handshake's few frames fit in the burst; only a
client that keeps the front end busy is slowed, to ``share`` of the interpreter.
"""

from __future__ import annotations

import asyncio
import time

SHARE = 0.2
"""The largest fraction of wall time one front end spends on its clients' frames when they keep it busy."""
BURST_S = 0.15
"""Work time a front end may spend at once before the pacing starts."""


class Pacer:
    """``t0 = await pacer.wait()`` before a frame's work and ``pacer.done(t0)`` after it (one event loop)."""

    def __init__(self, share: float = SHARE, burst_s: float = BURST_S) -> None:
        self.share, self.burst_s = share, burst_s
        self._credit = burst_s
        self._at = time.perf_counter()
        self.waited_s = 0.0

    def _refill(self) -> None:
        now = time.perf_counter()
        self._credit = min(self.burst_s, self._credit + (now - self._at) * self.share)
        self._at = now

    async def wait(self) -> float:
        """Wait until the budget allows more work; returns ``time.perf_counter()`` for :meth:`done`."""
        self._refill()
        if self._credit < 0:
            delay = -self._credit / self.share
            self.waited_s += delay
            await asyncio.sleep(delay)
            self._refill()
        return time.perf_counter()

    def done(self, t0: float) -> None:
        self._refill()
        self._credit -= time.perf_counter() - t0
