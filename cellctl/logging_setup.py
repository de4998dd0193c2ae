"""Logging of the service: plain text for a terminal, one JSON object per line for a log collector.

``configure_logging("json")`` makes every record (ours, uvicorn's, the drivers') a single JSON line
with ``time`` (UTC, ISO 8601, milliseconds), ``level``, ``logger``, ``message``, the ``request_id``
of the HTTP request being served (set by ``cellctl.api.middleware`` in ``request_id_var``) and any
extras given with ``log.info(..., extra={...})``. A traceback goes into ``exc``, as one string, so
a record never spans lines. ``cellctl serve`` picks text when stderr is a terminal and JSON
otherwise (under systemd, in a container, piped to a file), unless ``--log-format`` says.
"""

from __future__ import annotations

import json
import logging
import sys
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
