"""Edge guards against hostile requests, applied before routing, parsing and the route's own code.

- **Body size**: a body larger than ``http.max_body_mb`` is refused with 413 — at once when its
  ``Content-Length`` says so (nothing is read), else as soon as the streamed bytes pass the limit
  (what was read is dropped); the connection is closed rather than the rest read.
- **Slow bodies**: a body that has not arrived whole within ``http.body_timeout_s`` is refused
  with 408 and the connection closed (a client that trickles its body holds nothing longer).
- **Event streams**: requests for an event-stream route (``GET .../events``) and any response of
  type ``text/event-stream`` are counted per token and over all callers while they are open; one
  over ``http.max_event_streams_per_token`` / ``http.max_event_streams`` is refused with 429 —
  for the routes, before routing, so a burst costs no worker threads. (Each open stream
  holds a worker thread while it waits for events: an unbounded number starves every other route.)

The token, the role and the body's JSON are checked by ``cellctl.api.middleware`` (with
``cellctl.api.body``) in that order: no body is read before its caller is known.
Pure ASGI, used by ``cellctl.api.middleware.RequestMiddleware``.
"""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass
from typing import Any

from starlette.types import Message, Receive, Scope

from cellctl.errors import CellctlError

UNAUTHORIZED = 401
REQUEST_TIMEOUT = 408
BODY_TOO_LARGE = 413
UNPROCESSABLE = 422
TOO_MANY = 429
CLIENT_CLOSED = 499
"""Not sent (nobody is there to read it): the status logged and counted for a client that left mid-body."""

@dataclass(frozen=True)
class EdgeLimits:
    """The limits of the edge guards (``http`` section of cell.yaml)."""

    max_body_bytes: int = 8_000_000
    max_event_streams: int = 16
    max_event_streams_per_token: int = 4
    body_timeout_s: float = 5.0

    @classmethod
    def from_http_config(cls, http: Any) -> EdgeLimits:
        return cls(int(http.max_body_mb * 1e6), int(http.max_event_streams), int(http.max_event_streams_per_token),
                   float(http.body_timeout_s))


def error_message(status: int, code: str, message: str, extra_headers: list[tuple[bytes, bytes]] | None = None
                  ) -> tuple[Message, Message]:
    """The two ASGI messages of a JSON error response ``{"error": {"code", "message"}}``."""
    body = json.dumps({"error": {"code": code, "message": message}}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
               *(extra_headers or [])]
    return ({"type": "http.response.start", "status": status, "headers": headers},
            {"type": "http.response.body", "body": body, "more_body": False})


def _header(scope: Scope, name: bytes) -> bytes | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return bytes(value)
    return None


def too_large_text(limit_bytes: int, what: str) -> str:
    return (f"the request body {what} the limit of {limit_bytes / 1e6:g} MB; send a smaller body "
            "(or raise http.max_body_mb in cell.yaml)")


def declared_length(scope: Scope) -> int | None:
    """The request's ``Content-Length`` (None when absent or not a number)."""
    raw = _header(scope, b"content-length")
    if raw is None:
        return None
    try:
        return int(raw.strip())
    except ValueError:
        return None


def has_body(scope: Scope) -> bool:
    length = declared_length(scope)
    if length is not None:
        return length > 0
    return _header(scope, b"transfer-encoding") is not None


class BodyTooLarge(CellctlError):
    """The streamed body passed the limit (raised by :func:`read_body`)."""


class ClientGone(CellctlError):
    """The client disconnected before its body was complete."""


async def read_body(receive: Receive, limit_bytes: int) -> bytes:
    """The whole request body; ``BodyTooLarge`` as soon as it passes ``limit_bytes``."""
    chunks: list[bytes] = []
    total = 0
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            raise ClientGone
        chunk = message.get("body", b"")
        total += len(chunk)
        if total > limit_bytes:
            raise BodyTooLarge
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks)


def replaying(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that gives the app ``body`` in one message, then the client's own messages."""
    given = False

    async def replay() -> Message:
        nonlocal given
        if not given:
            given = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


class StreamLimiter:
    """Counts open event streams per token and over all callers (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._per_key: dict[str, int] = {}
        self._total = 0

    def acquire(self, key: str, limits: EdgeLimits) -> str | None:
        """Take a slot for ``key``; None when taken, else the reason it is refused."""
        with self._lock:
            refusal = self._refusal(key, limits)
            if refusal is None:
                self._per_key[key] = self._per_key.get(key, 0) + 1
                self._total += 1
            return refusal

    def _refusal(self, key: str, limits: EdgeLimits) -> str | None:
        mine = self._per_key.get(key, 0)
        if mine >= limits.max_event_streams_per_token:
            return (f"this token has {mine} event streams open, the limit per token is "
                    f"{limits.max_event_streams_per_token}: close one (each followed job holds one) "
                    "and retry, or raise http.max_event_streams_per_token in cell.yaml")
        if self._total >= limits.max_event_streams:
            return (f"{self._total} event streams are open, the cell's limit is {limits.max_event_streams}: "
                    "retry later, or raise http.max_event_streams in cell.yaml")
        return None

    def release(self, key: str) -> None:
        with self._lock:
            left = self._per_key.get(key, 0) - 1
            if left > 0:
                self._per_key[key] = left
            else:
                self._per_key.pop(key, None)
            self._total = max(0, self._total - 1)

    @property
    def open_streams(self) -> int:
        with self._lock:
            return self._total


def stream_key(scope: Scope) -> str:
    """Who holds a stream: a hash of the request's bearer token ("-" without any).

    Only the token counts (not the scheme's spelling or the spaces around it), so one token cannot
    open more streams by writing its header differently.
    """
    raw = _header(scope, b"authorization")
    parts = raw.split() if raw else []
    return hashlib.sha256(parts[-1]).hexdigest()[:16] if parts else "-"


def is_event_stream(message: Message) -> bool:
    for key, value in message.get("headers", ()):
        if bytes(key).lower() == b"content-type":
            return bytes(value).split(b";", 1)[0].strip().lower() == b"text/event-stream"
    return False


class StreamRefused(CellctlError):
    """Raised into the app when its event stream is refused (the 429 has been sent)."""
