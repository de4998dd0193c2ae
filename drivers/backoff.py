"""Reconnect back-off and outage counting, shared by every adapter that reconnects by itself.

``Backoff`` spaces reconnect attempts: the first waits ``initial_s``, each failure doubles the
wait up to ``max_s``, a success starts again from ``initial_s`` (pymodbus's ``reconnect_delay`` /
``reconnect_delay_max`` pattern). Loops that sleep between attempts take ``next_wait_s()``;
callers that attempt on demand ``schedule()`` after a failure and ask ``due()`` / ``remaining_s()``.

``Outages`` counts outages for ``health()``: one per transition from up to down (a device that
never came up has had no outage yet), with the duration of the last one that ended.

Times are seconds of ``time.monotonic`` (a different ``clock`` can be given, e.g. in tests).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from drivers.errors import DeviceInitError
from drivers.health import DeviceHealth


class Backoff:
    """Exponential back-off between reconnect attempts (seconds)."""

    def __init__(self, initial_s: float, max_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not 0 < initial_s <= max_s:
            raise DeviceInitError(f"reconnect back-off needs 0 < initial ({initial_s} s) <= max ({max_s} s); "
                                  "fix reconnect_initial_s / reconnect_max_s in cell.yaml")
        self.initial_s = initial_s
        self.max_s = max_s
        self._clock = clock
        self._delay_s = initial_s
        self._next_s: float | None = None

    @property
    def delay_s(self) -> float:
        """The wait before the next attempt, should the current one fail."""
        return self._delay_s

    def next_wait_s(self) -> float:
        """The wait before the next attempt; the one after a further failure is twice as long (capped)."""
        wait = self._delay_s
        self._delay_s = min(self._delay_s * 2.0, self.max_s)
        return wait

    def schedule(self) -> float:
        """An attempt failed: the next one is due after ``next_wait_s()``; returns that wait."""
        wait = self.next_wait_s()
        self._next_s = self._clock() + wait
        return wait

    @property
    def scheduled(self) -> bool:
        return self._next_s is not None

    def due(self) -> bool:
        """True when no attempt is scheduled or its time has come."""
        return self._next_s is None or self._clock() >= self._next_s

    def remaining_s(self) -> float:
        """Seconds until the scheduled attempt (0 when due)."""
        return 0.0 if self._next_s is None else max(0.0, self._next_s - self._clock())

    def reset(self) -> None:
        """A connection succeeded: the next failure waits ``initial_s`` again."""
        self._delay_s = self.initial_s
        self._next_s = None


class Outages:
    """Outage bookkeeping for ``health()``: count, reason, last outage duration (thread-safe)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._up = False
        self._since: float | None = None
        self.count = 0
        self.reconnects = 0
        self.last_outage_s = 0.0
        self.reason = "not connected"

    @property
    def is_up(self) -> bool:
        return self._up

    def up(self) -> None:
        """The device works (again): an open outage ends and its duration is kept."""
        with self._lock:
            if self._since is not None:
                self.last_outage_s = self._clock() - self._since
                self._since = None
            self._up = True
            self.reason = ""

    def down(self, reason: str, since_s: float | None = None) -> bool:
        """The device failed (``reason``); True when this opened a new outage (counted once).

        ``since_s`` (clock time) is when it really stopped working, if known earlier than now.
        """
        with self._lock:
            self.reason = reason
            if not self._up:
                return False
            self._up = False
            self._since = self._clock() if since_s is None else since_s
            self.count += 1
            return True

    def reconnected(self) -> None:
        """Count one reconnect attempt."""
        with self._lock:
            self.reconnects += 1

    def health(self, available: bool, **details: Any) -> DeviceHealth:
        """A ``DeviceHealth`` with these counters; ``reason`` is the last failure's when unavailable."""
        reason = details.pop("reason", None)
        return DeviceHealth(available=available, reason="" if available else (reason or self.reason),
                            outages=self.count, reconnects=self.reconnects, **details)
