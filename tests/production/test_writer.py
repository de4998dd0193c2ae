"""The run's store writer: writes in order on its thread; ``submit`` hands a write's result or error back."""

from __future__ import annotations

import pytest

from cellctl.production.writer import Writer


def test_submit_runs_in_order_with_the_queued_writes_and_returns_the_result_or_the_error() -> None:
    w = Writer("test-writer")
    try:
        done: list[str] = []
        w.put(lambda: done.append("first"))
        def claim() -> int:
            done.append("claim")
            return len(done)

        stored = w.submit(claim)
        w.put(lambda: done.append("after"))
        assert stored.result(10.0) == 2

        def fails() -> None:
            raise RuntimeError("the store is full")

        failed = w.submit(fails)
        assert isinstance(failed.exception(10.0), RuntimeError)
        with pytest.raises(RuntimeError, match="the store is full"):
            failed.result()
        w.flush()
        assert done == ["first", "claim", "after"]
    finally:
        w.close()
