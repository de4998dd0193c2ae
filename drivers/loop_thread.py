"""An asyncio event loop in its own thread, for servers that must answer whatever the caller's thread does.

The PLC servers (Modbus TCP, OPC UA) and the simulated Modbus devices each run an asyncio server
beside synchronous code. ``LoopThread`` is the one way to do it: ``start(serve)`` runs ``serve()``
on a fresh loop in a daemon thread and returns once it has returned (the server listens), or
raises what it raised (a taken port, a bad certificate): a failed start is never silent.
``call`` runs a coroutine on the loop from another thread; ``stop(shutdown)`` runs the server's
shutdown on the loop, cancels what is left and joins the thread. It lives in ``drivers`` so that
both the simulated devices and ``cellctl`` can use it (``drivers`` imports no ``cellctl``).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Awaitable, Callable
from typing import Any

from drivers.errors import DriverError


class LoopNotRunning(DriverError, RuntimeError):
    """``call`` on a loop thread that was not started or has stopped."""


class LoopThread:
    """Runs ``serve()`` (which returns once listening), then the loop until ``stop``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    @property
    def running(self) -> bool:
        return self.loop is not None and self.loop.is_running()

    def start(self, serve: Callable[[], Awaitable[Any]], timeout_s: float = 20.0) -> None:
        """Start the thread and wait until ``serve()`` returned; raise what it raised, or ``TimeoutError``."""
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, args=(serve,), name=self.name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            # Not left running: the start is abandoned, its loop stopped (serve() ends with an error) and joined.
            loop, thread = self.loop, self._thread
            if loop is not None:
                with contextlib.suppress(RuntimeError):  # closed meanwhile: it ended by itself
                    loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout_s)
            self._thread = None
            raise TimeoutError(f"{self.name} did not start within {timeout_s:.0f} s")
        if self._error is not None:
            self._thread.join(5.0)
            self._thread = None
            raise self._error

    def _run(self, serve: Callable[[], Awaitable[Any]]) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(serve())
        except BaseException as exc:  # noqa: BLE001 - handed to start(), which raises it in the caller's thread
            self._error = exc
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            with contextlib.suppress(Exception):
                pending = asyncio.all_tasks(loop)
                for task in pending:
                    task.cancel()
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    def call(self, fn: Callable[[], Awaitable[Any]], timeout_s: float = 10.0) -> Any:
        """Run the coroutine ``fn()`` on the loop from another thread and wait for its result."""
        loop = self.loop
        if loop is None or not loop.is_running():
            raise LoopNotRunning(f"{self.name}: the event loop is not running (start it first)")

        async def run() -> Any:
            return await fn()

        return asyncio.run_coroutine_threadsafe(run(), loop).result(timeout_s)

    def stop(self, shutdown: Callable[[], Awaitable[Any]] | None = None, timeout_s: float = 10.0) -> None:
        """Run ``shutdown()`` on the loop (errors ignored: we are stopping), stop the loop, join the thread.

        Safe to call twice, and before ``start``.
        """
        loop, thread = self.loop, self._thread
        if loop is None or thread is None:
            return
        if loop.is_running():
            if shutdown is not None:
                with contextlib.suppress(Exception):
                    self.call(shutdown, timeout_s)
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout_s)
        self._thread = None
