"""An asyncio event loop in its own thread, for a PLC server that must answer whatever the REST side does."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Awaitable, Callable
from typing import Any


class LoopNotRunning(RuntimeError):
    """A coroutine was sent to a loop thread that has not been started."""


class LoopThread:
    """Runs ``serve()`` (which returns once listening) then the loop until ``stop(shutdown)``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def start(self, serve: Callable[[], Awaitable[None]], timeout_s: float = 20.0) -> None:
        """Start the thread and wait until ``serve()`` returned (raises what it raised)."""
        self._thread = threading.Thread(target=self._run, args=(serve,), name=self.name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"{self.name} did not start within {timeout_s:.0f} s")
        if self._error is not None:
            self._thread.join(5.0)
            raise self._error

    def _run(self, serve: Callable[[], Awaitable[None]]) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(serve())
        except BaseException as exc:  # noqa: BLE001 - reported by start()
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
        """Run a coroutine on the loop from another thread and wait for its result."""
        if self.loop is None:
            raise LoopNotRunning(f"{self.name} is not running: start() it first")
        return asyncio.run_coroutine_threadsafe(fn(), self.loop).result(timeout_s)  # type: ignore[arg-type]

    def stop(self, shutdown: Callable[[], Awaitable[None]] | None = None, timeout_s: float = 10.0) -> None:
        """Run ``shutdown()`` on the loop, stop the loop and join the thread."""
        loop = self.loop
        if loop is None or self._thread is None:
            return
        if loop.is_running():
            if shutdown is not None:
                with contextlib.suppress(Exception):
                    self.call(shutdown, timeout_s)
            loop.call_soon_threadsafe(loop.stop)
        self._thread.join(timeout_s)
        self._thread = None
