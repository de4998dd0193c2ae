"""A job's event stream ends with its end state: a reader that sees the job no longer running still
gets the final ``state`` event (the end hooks, e.g. halting the robot, run between the two)."""

from __future__ import annotations

import threading
from typing import Any

from cellctl.jobs import JobContext, JobManager


def test_the_stream_is_whole_only_once_the_end_state_is_out() -> None:
    hooks_may_end = threading.Event()

    def routine(ctx: JobContext) -> dict[str, Any]:
        ctx.report(0.5, "half way")
        def slow_hook() -> None:  # an end hook that takes its time
            hooks_may_end.wait(10.0)

        ctx.on_end.append(slow_hook)
        return {}

    jobs = JobManager()
    job = jobs.start("slow-end", routine, {}, "test")
    try:
        seen = job.events_after(-1, 5.0)
        while job.state == "running":  # the routine returned; its end hook holds the final event back
            threading.Event().wait(0.01)
        assert not job.closed  # no longer running, yet its stream is not whole
        waiter = threading.Timer(0.2, hooks_may_end.set)
        waiter.start()
        more = job.events_after(seen[-1].seq, 5.0)  # waits for the end state instead of answering at once
        assert [e.kind for e in more] == ["state"] and more[0].data["state"] == "succeeded"
        assert job.closed
    finally:
        hooks_may_end.set()
        jobs.shutdown()
