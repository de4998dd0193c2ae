"""A pymodbus server of a simulated peer, on an event-loop thread of its own: start once, stop safely."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from drivers.loop_thread import LoopThread


class ServedModbus:
    """Runs the server ``make()`` builds (inside the loop, as pymodbus wants) until ``stop``."""

    def __init__(self, thread_name: str) -> None:
        self._server: Any = None
        self._loop_thread = LoopThread(thread_name)

    def start(self, make: Callable[[], Any], failure: str) -> None:
        """Serve; any way the server fails to start is one ``OSError`` beginning with ``failure``."""

        async def serve() -> None:
            self._server = make()
            await self._server.serve_forever(background=True)

        try:
            self._loop_thread.start(serve, timeout_s=10.0)
        except Exception as exc:  # noqa: BLE001 - one clear error for every way the server fails to start
            raise OSError(f"{failure}: {exc}") from exc

    def stop(self) -> None:
        server = self._server
        self._loop_thread.stop(server.shutdown if server is not None else None, timeout_s=5.0)
