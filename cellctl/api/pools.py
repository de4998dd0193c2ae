"""Worker-thread pools: which blocking work may wait for which threads.

Blocking calls (a device, the store, a large body's parse) run in worker threads so the event loop
keeps serving. Threads are a shared resource a flood can use up, so the work is split into pools
(anyio capacity limiters) that cannot starve each other:

- **safety**: the routes a person or a PLC relies on to stop the cell — ``POST .../stop``,
  ``POST .../resume``, ``GET .../state``, ``GET .../motion`` and ``GET /health``
  (:data:`SAFETY_ROUTES`). Their device and store calls run here and nowhere else; their
  dependencies (token, role) run on the event loop without a thread.
- **body**: parsing and validating request bodies of :data:`OFF_LOOP_BYTES` or more (at most
  :data:`BODY_THREADS` at a time; more wait, without a thread, for their turn).
- everything else: anyio's default pool (40 threads), as Starlette and FastAPI use it.

The middleware sets :data:`pool_var` for each request from its route; ``device_call`` and
:func:`run_blocking` use the pool it names.
"""

from __future__ import annotations

import contextvars
import functools
from collections.abc import Callable
from typing import Any, TypeVar

import anyio.to_thread
from anyio import CapacityLimiter

T = TypeVar("T")

SAFETY_ROUTES = frozenset({"/robots/{robot_id}/stop", "/robots/{robot_id}/resume", "/robots/{robot_id}/state",
                           "/robots/{robot_id}/motion", "/health"})
"""Route templates served from the safety pool."""
SAFETY_THREADS = 8
BODY_THREADS = 2
OFF_LOOP_BYTES = 8_000
"""Bodies at least this large are parsed and validated in the body pool, never on the event loop
(54 kB of numbers took ~30 ms to parse on the loaded 2-core machine; 8 kB is a few ms)."""


class Pools:
    """The service's own pools (made per app: a limiter belongs to the event loop that uses it)."""

    def __init__(self) -> None:
        self.safety = CapacityLimiter(SAFETY_THREADS)
        self.body = CapacityLimiter(BODY_THREADS)


pool_var: contextvars.ContextVar[CapacityLimiter | None] = contextvars.ContextVar("cellctl_pool", default=None)
"""The pool of the request being served (None: the default pool)."""


async def run_blocking(fn: Callable[..., T], *args: Any, pool: CapacityLimiter | None = None) -> T:
    """``fn(*args)`` in a worker thread of ``pool`` (default: the request's pool); anyio carries the
    context variables (the request id) into the thread."""
    limiter = pool if pool is not None else pool_var.get()
    return await anyio.to_thread.run_sync(functools.partial(fn, *args), limiter=limiter)
