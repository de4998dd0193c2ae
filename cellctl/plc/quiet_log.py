"""Logging for the PLC front ends under hostile input: one line per client mistake, no traceback, and
at most a burst of lines per window for the same kind of mistake (the rest are counted and
summarised once the window is over). A client's garbage must not grow the log without bound.

:class:`QuietFilter` goes on the protocol libraries' loggers (pymodbus, cpppo): it cuts each record
to its first line, drops the traceback and rate-limits by message; :func:`client_mistake` is the
front ends' own rate-limited warning.
"""

from __future__ import annotations

import logging
import re
import threading
import time

WINDOW_S = 10.0
BURST = 5
MAX_CHARS = 240
_DIGITS = re.compile(r"[0-9]+")


class _Limiter:
    """At most ``burst`` records per ``window_s`` per key; then one summary of how many were dropped."""

    def __init__(self, window_s: float = WINDOW_S, burst: int = BURST) -> None:
        self.window_s, self.burst = window_s, burst
        self._lock = threading.Lock()
        self._windows: dict[str, tuple[float, int]] = {}

    def allow(self, key: str) -> tuple[bool, int]:
        """Whether to log this one, and how many of this key were dropped in the window just over."""
        now = time.monotonic()
        with self._lock:
            start, n = self._windows.get(key, (now, 0))
            dropped = 0
            if now - start >= self.window_s:
                dropped = max(0, n - self.burst)
                start, n = now, 0
            n += 1
            self._windows[key] = (start, n)
            if len(self._windows) > 1000:  # keys are message texts: keep the table small
                self._windows = {k: v for k, v in self._windows.items() if now - v[0] < self.window_s}
            return n <= self.burst, dropped


class QuietFilter(logging.Filter):
    """First line only, no traceback, rate-limited by message (for a protocol library's logger)."""

    def __init__(self, window_s: float = WINDOW_S, burst: int = BURST) -> None:
        super().__init__()
        self._limiter = _Limiter(window_s, burst)

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 - a bad format string in a library's record
            text = str(record.msg)
        first = (text.strip().splitlines() or [""])[0][:MAX_CHARS]
        # The same kind of message with other numbers in it (a protocol id, a length) is one key.
        ok, dropped = self._limiter.allow(f"{record.name}:{_DIGITS.sub('#', first)[:40]}")
        if not ok:
            return False
        record.msg = first + (f" (and {dropped} more like it in the last {self._limiter.window_s:.0f} s)"
                              if dropped else "")
        record.args = None
        record.exc_info = None
        record.exc_text = None
        record.stack_info = None
        return True


_installed: set[str] = set()
_install_lock = threading.Lock()


def quiet(logger_name: str, level: int = logging.WARNING) -> None:
    """Put a :class:`QuietFilter` on a library's logger and on every child logger it has made so far (a
    logger's filters do not apply to its children's records), and raise its level to at least ``level``."""
    with _install_lock:
        logger = logging.getLogger(logger_name)
        names = [logger_name] + [n for n in list(logging.root.manager.loggerDict)
                                 if n.startswith(logger_name + ".")]
        for name in names:
            if name not in _installed:
                logging.getLogger(name).addFilter(QuietFilter())
                _installed.add(name)
        if logger.getEffectiveLevel() < level:
            logger.setLevel(level)


_mistakes = _Limiter()


def client_mistake(log: logging.Logger, kind: str, message: str, *args: object) -> None:
    """A warning about a client's mistake (bad frame, over-long line, too many connections), rate-limited
    per ``kind``; never a traceback."""
    ok, dropped = _mistakes.allow(f"{log.name}:{kind}")
    if not ok:
        return
    suffix = f" (and {dropped} more {kind} in the last {WINDOW_S:.0f} s)" if dropped else ""
    log.warning(message + suffix, *args)
