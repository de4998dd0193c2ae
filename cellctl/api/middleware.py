"""Per-request bookkeeping: a request id, the latency metric and one access-log line.

A pure ASGI middleware (not Starlette's ``BaseHTTPMiddleware``), so server-sent event streams pass
through untouched. The request id is the caller's ``X-Request-Id`` when it is safe to echo and log
(``cellctl.api.request_id``: letters, digits, ``._:-``, at most 64 characters, no credential in it),
otherwise a fresh random one; it is echoed in
the response's ``X-Request-Id`` header and set in ``cellctl.logging_setup.request_id_var`` for every
log record written while the request is served. Latency runs from the request's arrival to the
last byte of the response (for an SSE stream: until the stream ends).

It also is the service's edge: before the app sees a request, in this order,

1. a declared body over ``http.max_body_mb`` is refused (413), nothing read;
2. the route's token and role are checked (401, 403) from the headers alone — no body is read or
   parsed for a caller who may not call the route (an open route takes no body: it is never read);
3. the body is read within ``http.body_timeout_s`` (408 for a slow one; a client that leaves
   mid-body is logged and counted as 499, a client error) and up to the size limit (413);
4. its JSON is parsed once and bounded (``cellctl.api.body``: non-finite or overlong numbers,
   depth, value count: 422 naming the field) — a large body in the body pool, never on the loop;
5. event streams are counted (429 over ``http.max_event_streams*``).

Refusals that leave a body unread close the connection rather than read the rest. Each request
runs its blocking work in its route's pool (``cellctl.api.pools``: Stop, resume, state and
``/health`` in the safety pool). Limits come from the config's ``http`` section (or ``limits``).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import anyio
from starlette.datastructures import MutableHeaders
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from cellctl.api.body import PARSED_KEY, inspect_body
from cellctl.api.deps import PRINCIPAL_KEY, authenticate, role_refusal
from cellctl.api.edge_routes import RouteInfo, RouteTable
from cellctl.api.errors import ApiError
from cellctl.api.guards import (
    BODY_TOO_LARGE,
    CLIENT_CLOSED,
    REQUEST_TIMEOUT,
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
    read_body,
    replaying,
    stream_key,
    too_large_text,
)
from cellctl.api.pools import OFF_LOOP_BYTES, Pools, pool_var, run_blocking
from cellctl.api.request_id import incoming_request_id, new_request_id
from cellctl.logging_setup import request_id_var
from cellctl.metrics import CellMetrics

access_log = logging.getLogger("cellctl.access")

REQUEST_ID_HEADER = "X-Request-Id"
UNMATCHED = "unmatched"
EDGE = "edge"
"""The route label of a request the edge guards answered (never routed)."""


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
        self._routes: RouteTable | None = None
        self._pools: Pools | None = None

    def limits(self, scope: Scope) -> EdgeLimits:
        """The edge limits: given ones, else the serving app's ``config.http``, else the defaults."""
        if self._limits is None:
            config = getattr(getattr(scope.get("app"), "state", None), "config", None)
            http = getattr(config, "http", None)
            self._limits = EdgeLimits.from_http_config(http) if http is not None else EdgeLimits()
        return self._limits

    def routes(self, scope: Scope) -> RouteTable:
        if self._routes is None:
            self._routes = RouteTable(scope["app"])
        return self._routes

    def pools(self, scope: Scope) -> Pools:
        """The app's pools (``app.state.pools``), else the middleware's own."""
        if self._pools is None:
            found = getattr(getattr(scope.get("app"), "state", None), "pools", None)
            self._pools = found if isinstance(found, Pools) else Pools()
        return self._pools

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        rid = incoming_request_id(scope) or new_request_id()
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
            at_edge, unsent = await self._guarded(scope, receive, send_with_id)
            if unsent is not None:
                status = unsent
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

    async def _guarded(self, scope: Scope, receive: Receive, send: Send) -> tuple[bool, int | None]:
        """Run the edge's checks, then the app. ``(answered at the edge, status when none could be sent)``."""
        limits = self.limits(scope)
        pending = has_body(scope)
        length = declared_length(scope)
        if pending and length is not None and length > limits.max_body_bytes:
            await _answer(send, BODY_TOO_LARGE, "body_too_large",
                          too_large_text(limits.max_body_bytes, f"of {length / 1e6:.1f} MB is over"), CLOSE)
            return True, None
        route = self.routes(scope).match(scope)
        token = pool_var.set(self.pools(scope).safety if route is not None and route.safety else None)
        try:
            if route is not None and route.role is not None:
                refusal = self._refusal(scope, route)
                if refusal is not None:
                    await _answer(send, refusal.status, refusal.code, refusal.message, CLOSE if pending else None)
                    return True, None
                if pending:
                    outcome, receive = await self._take_body(scope, receive, send, limits)
                    if outcome is not None:
                        return True, (None if outcome == ANSWERED else outcome)
            elif pending:
                send = _closing(send)  # the app answers (404, 405, an open route) without reading it
            return await self._streams_and_app(scope, receive, send, limits), None
        finally:
            pool_var.reset(token)

    def _refusal(self, scope: Scope, route: RouteInfo) -> ApiError | None:
        """401/403 for a caller who may not call ``route`` (from the headers alone), else None."""
        auth = None
        for key, value in scope.get("headers", ()):
            if key.lower() == b"authorization":
                auth = bytes(value).decode("latin-1")
        found = authenticate(scope["app"].state.tokens, auth)
        if isinstance(found, ApiError):
            return found
        scope[PRINCIPAL_KEY] = found
        return role_refusal(found, route.role) if route.role is not None else None

    async def _take_body(self, scope: Scope, receive: Receive, send: Send, limits: EdgeLimits
                         ) -> tuple[int | None, Receive]:
        """Read, bound and parse the body. ``(None, receive replaying it)``, or the outcome when refused
        (``ANSWERED``, or the status of a client that left)."""
        try:
            with anyio.fail_after(limits.body_timeout_s):
                body = await read_body(receive, limits.max_body_bytes)
        except TimeoutError:
            await _answer(send, REQUEST_TIMEOUT, "body_timeout",
                          f"the request body did not arrive within {limits.body_timeout_s:g} s "
                          "(http.body_timeout_s in cell.yaml); send it at once, or raise the limit", CLOSE)
            return ANSWERED, receive
        except BodyTooLarge:
            await _answer(send, BODY_TOO_LARGE, "body_too_large", too_large_text(limits.max_body_bytes, "passed"),
                          CLOSE)
            return ANSWERED, receive
        except ClientGone:
            access_log.info("the client closed the connection before its request body was complete")
            return CLIENT_CLOSED, receive
        if len(body) < OFF_LOOP_BYTES:
            parsed, problem = inspect_body(body)
        else:
            parsed, problem = await run_blocking(inspect_body, body, True, pool=self.pools(scope).body)
        if problem is not None:
            await _answer(send, UNPROCESSABLE, "invalid_request", problem)
            return ANSWERED, receive
        if parsed is not None:
            scope[PARSED_KEY] = parsed
        return None, replaying(body, receive)

    async def _streams_and_app(self, scope: Scope, receive: Receive, send: Send, limits: EdgeLimits) -> bool:
        """Count event streams (429 over the limits: True), else run the app (False)."""
        held: str | None = None
        if scope.get("method") == "GET" and str(scope.get("path", "")).endswith("/events"):
            # An event-stream route: the slot is taken before routing, so a burst of requests is
            # refused here without costing a worker thread each (an answer that is not a stream,
            # e.g. 404, gives the slot back as soon as it is sent).
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


ANSWERED = 0
"""An edge outcome: the refusal has been sent."""


def _closing(send: Send) -> Send:
    """``send`` that marks the response ``Connection: close`` (the server then drops the unread body)."""

    async def closing(message: Message) -> None:
        if message["type"] == "http.response.start":
            MutableHeaders(scope=message)["connection"] = "close"
        await send(message)

    return closing


# The server closes the connection after a refused body instead of reading the rest of it.
CLOSE = [(b"connection", b"close")]


async def _answer(send: Send, status: int, code: str, message: str,
                  headers: list[tuple[bytes, bytes]] | None = None) -> None:
    start, body = error_message(status, code, message, headers)
    await send(start)
    await send(body)
