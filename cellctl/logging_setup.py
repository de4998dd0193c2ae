"""Logging of the service: plain text for a terminal, one JSON object per line for a log collector.

``configure_logging("json")`` makes every record (ours, uvicorn's, the drivers') a single JSON line
with ``time`` (UTC, ISO 8601, milliseconds), ``level``, ``logger``, ``message``, the ``request_id``
of the HTTP request being served (set by ``cellctl.api.middleware`` in ``request_id_var``) and any
extras given with ``log.info(..., extra={...})``. A traceback goes into ``exc``, as one string, so
a record never spans lines. ``cellctl serve`` picks text when stderr is a terminal and JSON
otherwise (under systemd, in a container, piped to a file), unless ``--log-format`` says.

What a flood of clients makes happen must not flood the log (issue 34: 53-94 MB in 20 s while
the process was out of descriptors). Two filters sit on the handler:

- :class:`RepeatFilter`: the same message (logger, level and, for warnings and errors, the format
  string — for information, the text) is written at most ``REPEAT_MAX`` (20) times per
  ``REPEAT_WINDOW_S`` (10 s); the rest are counted, and the first one after the window says how
  many were left out (``"... (and 1234 more like this in the last 10 s)"``,
  with ``suppressed`` as an extra).
- :class:`ClientNoiseFilter`: a record caused by a client's garbage or a vanished peer (a reset
  connection, a TLS handshake of junk, an invalid HTTP request) or by the process running out of
  descriptors carries no traceback: its exception's type and text are appended to the message.
"""

from __future__ import annotations

import errno
import json
import logging
import ssl
import sys
import threading
import time
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import Any, Literal, TextIO

LogFormat = Literal["json", "text"]

request_id_var: ContextVar[str | None] = ContextVar("cellctl_request_id", default=None)
"""The id of the request being served in this context (None outside requests)."""

# Attributes every LogRecord has; anything else on a record came from ``extra=``.
_STANDARD_ATTRS = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {
    "message", "asctime", "taskName",
    "color_message",  # uvicorn's copy of the message with terminal colour codes
}
TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s [%(request_id)s] %(message)s"


class RequestIdFilter(logging.Filter):
    """Puts the current request id on every record (``-`` outside a request) for the text format."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "request_id"):
            record.request_id = request_id_var.get() or "-"
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds").replace(
                "+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        rid = getattr(record, "request_id", None)
        if rid in (None, "-"):
            rid = request_id_var.get()
        if rid is not None:
            out["request_id"] = rid
        for key, value in vars(record).items():
            if key not in _STANDARD_ATTRS and key not in out and key != "request_id":
                out[key] = value
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exc"] = record.exc_text
        if record.stack_info:
            out["stack"] = self.formatStack(record.stack_info)
        return json.dumps(out, default=str, ensure_ascii=False)


REPEAT_MAX = 20
REPEAT_WINDOW_S = 10.0
_MAX_KEYS = 4096


class RepeatFilter(logging.Filter):
    """At most ``max_per_window`` records of one message per ``window_s``; the rest counted, then summarised."""

    def __init__(self, max_per_window: int = REPEAT_MAX, window_s: float = REPEAT_WINDOW_S) -> None:
        super().__init__()
        self.max_per_window = max_per_window
        self.window_s = window_s
        self._seen: dict[tuple[str, int, str], list[float]] = {}  # key -> [window start, written, left out]
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        # Warnings and errors by their format string (a flood's "refused: %s" lines are one message);
        # information by its text (each access-log line differs; only exact repeats are counted).
        text = str(record.msg) if record.levelno >= logging.WARNING else record.getMessage()
        key = (record.name, record.levelno, text)
        now = time.monotonic()
        with self._lock:
            entry = self._seen.get(key)
            if entry is None or now - entry[0] >= self.window_s:
                left_out = int(entry[2]) if entry is not None else 0
                if entry is None and len(self._seen) >= _MAX_KEYS:
                    self._forget(now)
                self._seen[key] = [now, 1, 0]
                if left_out:
                    record.msg = f"{record.msg} (and {left_out} more like this in the last {self.window_s:g} s)"
                    record.suppressed = left_out
                return True
            if entry[1] < self.max_per_window:
                entry[1] += 1
                return True
            entry[2] += 1
            return False

    def _forget(self, now: float) -> None:
        """Drop the keys whose window has passed (a bounded table, whatever the messages)."""
        for k in [k for k, e in self._seen.items() if now - e[0] >= self.window_s]:
            del self._seen[k]
        while len(self._seen) >= _MAX_KEYS:
            self._seen.pop(next(iter(self._seen)))


def _client_noise() -> tuple[type[BaseException], ...]:
    kinds: list[type[BaseException]] = [ConnectionError, ssl.SSLError, TimeoutError]
    try:
        import h11

        kinds.append(h11.RemoteProtocolError)
    except ImportError:  # pragma: no cover - uvicorn brings h11
        pass
    return tuple(kinds)


_NOISE = _client_noise()
_OUT_OF_DESCRIPTORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


class ClientNoiseFilter(logging.Filter):
    """No traceback for what a client (or descriptor exhaustion) caused: the exception in one phrase instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        info = record.exc_info
        exc = info[1] if info else None
        if exc is not None and (isinstance(exc, _NOISE) or (isinstance(exc, OSError)
                                                           and exc.errno in _OUT_OF_DESCRIPTORS)):
            record.msg = f"{record.getMessage()} ({type(exc).__name__}: {exc})"
            record.args = None
            record.exc_info = None
            record.exc_text = None
        return True


def default_format(stream: TextIO | None = None) -> LogFormat:
    """Text on a terminal, JSON otherwise."""
    s = stream if stream is not None else sys.stderr
    try:
        return "text" if s.isatty() else "json"
    except (AttributeError, ValueError):
        return "json"


def configure_logging(fmt: LogFormat | None = None, level: int | str = logging.INFO,
                      stream: TextIO | None = None) -> logging.Handler:
    """Route all logging (root, uvicorn's loggers included) to one handler in the chosen format.

    Replaces the root logger's handlers; uvicorn's own handlers are removed so its records
    propagate here and are formatted like ours. Returns the handler.
    """
    fmt = fmt or default_format(stream)
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.addFilter(RepeatFilter())  # keyed by the format string, before the next one rewrites it
    handler.addFilter(ClientNoiseFilter())
    handler.addFilter(RequestIdFilter())
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    elif fmt == "text":
        handler.setFormatter(logging.Formatter(TEXT_FORMAT))
    else:
        raise ValueError(f"unknown log format {fmt!r}; use json or text")
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        lg = logging.getLogger(name)
        for old in list(lg.handlers):
            lg.removeHandler(old)
        lg.propagate = True
    return handler
