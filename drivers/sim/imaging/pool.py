"""The renderer's threads and per-thread scratch memory (``drivers.sim.imaging.renderer``'s private helpers)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_LOCAL = threading.local()
_T = TypeVar("_T")
_I = TypeVar("_I")


def parallel(fn: Callable[[_I], _T], items: Sequence[_I], threads: int) -> list[_T]:
    """``[fn(item) for item in items]``, the items handed out one by one to the calling thread and
    up to ``threads - 1`` pool workers (the compiled loops release the GIL, numpy mostly)."""
    global _POOL
    helpers = min(threads, len(items)) - 1
    if helpers <= 0:
        return [fn(item) for item in items]
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max(threads - 1, 1), thread_name_prefix="render")
        pool = _POOL
    todo = iter(range(len(items)))
    take = threading.Lock()
    out: list[_T | None] = [None] * len(items)

    def work() -> None:
        while True:
            with take:
                i = next(todo, None)
            if i is None:
                return
            out[i] = fn(items[i])

    futures = [pool.submit(work) for _ in range(helpers)]
    try:
        work()
    finally:
        for f in futures:
            f.result()  # waits; re-raises a helper's error
    return out  # type: ignore[return-value]


class Scratch:
    """Compacted hits of one chunk: object x, y (m), depth (m) and the flat ray index; and the
    sub-ray buffers of supersampling (value, depth, object)."""

    def __init__(self) -> None:
        self.ox = self.oy = self.lam = np.empty(0)
        self.flat = np.empty(0, dtype=np.int64)
        self.sub_value = self.sub_depth = np.empty(0)
        self.sub_which = np.empty(0, dtype=np.int32)

    @property
    def hits(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        return self.ox, self.oy, self.lam, self.flat

    def ensure(self, size: int) -> None:
        if self.ox.size < size:
            self.ox, self.oy, self.lam = np.empty(size), np.empty(size), np.empty(size)
            self.flat = np.empty(size, dtype=np.int64)

    def ensure_sub(self, size: int) -> None:
        if self.sub_value.size < size:
            self.sub_value, self.sub_depth = np.empty(size), np.empty(size)
            self.sub_which = np.empty(size, dtype=np.int32)


def scratch(size: int) -> Scratch:
    """This thread's scratch, at least ``size`` rays long."""
    mine: Scratch | None = getattr(_LOCAL, "scratch", None)
    if mine is None:
        mine = _LOCAL.scratch = Scratch()
    mine.ensure(size)
    return mine
