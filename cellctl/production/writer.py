"""A run's store writes off the cycle's critical path: one thread writes them in order.

Cycle records, the run's state, the next slot and the audit of every move are written by this
thread, so that a cycle does not wait for the database's fsyncs (a SQLite commit with
``synchronous=FULL`` takes milliseconds, and a cycle writes about ten rows). ``flush`` waits until
everything queued is written (the run calls it before it ends).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import TypeVar

T = TypeVar("T")

log = logging.getLogger(__name__)


class Writer:
    """Runs queued store writes in order in its own thread."""

    def __init__(self, name: str) -> None:
        self._q: queue.Queue[Callable[[], object] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def put(self, write: Callable[[], object]) -> None:
        self._q.put(write)

    def submit(self, write: Callable[[], T]) -> Future[T]:
        """Queue ``write`` in order with the others; its result (or its exception) for a caller that must
        know it was stored before going on (a slot's claim before the part goes down)."""
        done: Future[T] = Future()

        def run() -> None:
            try:
                done.set_result(write())
            except BaseException as exc:  # noqa: BLE001 - handed to the caller, who raises it
                done.set_exception(exc)

        self._q.put(run)
        return done

    def _loop(self) -> None:
        while True:
            write = self._q.get()
            try:
                if write is None:
                    return
                write()
            except Exception:  # noqa: BLE001 - a failed write is logged; the run goes on
                log.exception("production: a store write failed")
            finally:
                self._q.task_done()

    def flush(self) -> None:
        """Wait until every queued write is done."""
        self._q.join()

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(10.0)
