"""Per-request bookkeeping: a request id, the latency metric and one access-log line.

A pure ASGI middleware (not Starlette's ``BaseHTTPMiddleware``), so server-sent event streams pass
through untouched. The request id is the caller's ``X-Request-Id`` when it is a sane token
(letters, digits, ``._:-``, at most 128 characters), otherwise a fresh random one; it is echoed in
the response's ``X-Request-Id`` header and set in ``cellctl.logging_setup.request_id_var`` for every
log record written while the request is served. Latency runs from the request's arrival to the
last byte of the response (for an SSE stream: until the stream ends).

It also applies the edge guards of ``cellctl.api.guards`` before anything else sees the request:
the body size limit (413), non-finite JSON numbers (422) and the cap on open event streams (429),
with the limits of the config's ``http`` section (or ``limits`` when given).
"""

from __future__ import annotations

import logging
import re
import time
import uuid
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.datastructures import MutableHeaders
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from cellctl.api.guards import (
    BODY_TOO_LARGE,
    TOO_MANY,
    UNPROCESSABLE,
    BodyTooLarge,
    ClientGone,
    EdgeLimits,
    StreamLimiter,
    StreamRefused,
    declared_length,
    error_message,
    has_body,
    is_event_stream,
    non_finite_field,
    non_finite_text,
    read_body,
    replaying,
    stream_key,
    too_large_text,
)
from cellctl.logging_setup import request_id_var
from cellctl.metrics import CellMetrics

access_log = logging.getLogger("cellctl.access")

REQUEST_ID_HEADER = "X-Request-Id"
_SANE_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
UNMATCHED = "unmatched"
EDGE = "edge"
"""The route label of a request the edge guards answered (never routed)."""


def incoming_request_id(scope: Scope) -> str | None:
    """The caller's request id if it is safe to log and echo, else None."""
    for name, value in scope.get("headers", ()):
        if name.lower() == b"x-request-id":
            text = value.decode("latin-1").strip()
            return text if _SANE_ID.match(text) else None
    return None


def route_template(scope: Scope) -> str:
    """The path template of the route that served the request, e.g. ``/robots/{robot_id}/state``."""
    route = scope.get("route")
    path = getattr(route, "path", None)
    if isinstance(path, str) and path:
        return path
    app: Any = scope.get("app")
    router = getattr(app, "router", None)
    for r in getattr(router, "routes", ()):
        try:
            match, _ = r.matches(scope)
        except Exception:  # noqa: BLE001 - a route that cannot match this scope is not ours
            continue
        if match == Match.FULL:
            p = getattr(r, "path", None)
            if isinstance(p, str):
                return p or "/"
    return UNMATCHED


class RequestMiddleware:
    """Request id, latency histogram and access log for every HTTP request."""

    def __init__(self, app: ASGIApp, metrics: CellMetrics, limits: EdgeLimits | None = None) -> None:
        self.app = app
        self.metrics = metrics
        self._limits = limits
        self.streams = StreamLimiter()

    def limits(self, scope: Scope) -> EdgeLimits:
        """The edge limits: given ones, else the serving app's ``config.http``, else the defaults."""
        if self._limits is None:
            config = getattr(getattr(scope.get("app"), "state", None), "config", None)
            http = getattr(config, "http", None)
            self._limits = EdgeLimits.from_http_config(http) if http is not None else EdgeLimits()
        return self._limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        rid = incoming_request_id(scope) or uuid.uuid4().hex
        token = request_id_var.set(rid)
        start = time.perf_counter()
        status = 500  # what the caller gets when the app raises before answering

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                MutableHeaders(scope=message).append(REQUEST_ID_HEADER, rid)
            await send(message)

        failed = False
        at_edge = False
        try:
            at_edge = await self._guarded(scope, receive, send_with_id)
        except BaseException:
            failed = True
            raise
        finally:
            duration_s = time.perf_counter() - start
            route = EDGE if at_edge else route_template(scope)
            method = str(scope.get("method", "?"))
            try:
                self.metrics.observe_request(method, route, status, duration_s)
            except Exception:  # noqa: BLE001 - a metric must not break a request
                access_log.debug("request metric failed", exc_info=True)
            client = scope.get("client")
            access_log.info("%s %s %d %.1f ms", method, scope.get("path", ""), status, duration_s * 1e3,
                            extra={"method": method, "path": scope.get("path", ""), "route": route,
                                   "status": status, "duration_ms": round(duration_s * 1e3, 3),
                                   "client": f"{client[0]}:{client[1]}" if client else None})
            if not failed:
                # On failure the id stays set so the outer error handler's log line still carries it.
                request_id_var.reset(token)

    async def _guarded(self, scope: Scope, receive: Receive, send: Send) -> bool:
        """Refuse oversized bodies, non-finite JSON numbers and surplus event streams (True), else run the app."""
        limits = self.limits(scope)
        if has_body(scope):
            length = declared_length(scope)
            if length is not None and length > limits.max_body_bytes:
                await _answer(send, BODY_TOO_LARGE, "body_too_large",
                              too_large_text(limits.max_body_bytes, f"of {length / 1e6:.1f} MB is over"), CLOSE)
                return True
            try:
                body = await read_body(receive, limits.max_body_bytes)
            except BodyTooLarge:
                await _answer(send, BODY_TOO_LARGE, "body_too_large", too_large_text(limits.max_body_bytes, "passed"),
                              CLOSE)
                return True
            except ClientGone:
                return True  # nobody to answer
            # A large suspicious body is parsed off the event loop (other requests go on meanwhile).
            bad = (non_finite_field(body) if len(body) < OFF_LOOP_BYTES
                   else await run_in_threadpool(non_finite_field, body))
            if bad is not None:
                await _answer(send, UNPROCESSABLE, "invalid_request", non_finite_text(*bad))
                return True
            receive = replaying(body, receive)

        held: str | None = None
        if scope.get("method") == "GET" and str(scope.get("path", "")).endswith("/events"):
            # An event-stream route: the slot is taken before routing and auth, so a burst of
            # requests is refused here without costing a worker thread each (an answer that is
            # not a stream, e.g. 401 or 404, gives the slot back as soon as it is sent).
            key = stream_key(scope)
            refusal = self.streams.acquire(key, limits)
            if refusal is not None:
                await _answer(send, TOO_MANY, "too_many_streams", refusal, [(b"retry-after", b"5")])
                return True
            held = key

        async def send_counted(message: Message) -> None:
            nonlocal held
            if message["type"] == "http.response.start" and held is None and is_event_stream(message):
                key = stream_key(scope)
                refusal = self.streams.acquire(key, limits)
                if refusal is not None:
                    await _answer(send, TOO_MANY, "too_many_streams", refusal, [(b"retry-after", b"5")])
                    raise StreamRefused
                held = key
            await send(message)

        try:
            await self.app(scope, receive, send_counted)
        except StreamRefused:
            pass  # answered 429; the stream never started
        finally:
            if held is not None:
                self.streams.release(held)
        return False


OFF_LOOP_BYTES = 256_000
"""Bodies at least this large are checked for non-finite numbers in a worker thread."""

# The server closes the connection after a refused body instead of reading the rest of it.
CLOSE = [(b"connection", b"close")]


async def _answer(send: Send, status: int, code: str, message: str,
                  headers: list[tuple[bytes, bytes]] | None = None) -> None:
    start, body = error_message(status, code, message, headers)
    await send(start)
    await send(body)
