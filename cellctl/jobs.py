"""Long-running work as jobs: a thread each, progress events, cancellation, operator input.

A routine is a function ``fn(ctx: JobContext) -> dict`` run in its own thread. It reports
progress with ``ctx.report``; it calls ``ctx.check_cancelled()`` between steps (which raises
``JobCancelled`` once ``DELETE /jobs/{id}`` asked); it can wait for operator input
(``ctx.wait_input``) that ``POST /jobs/{id}/record`` delivers. Whatever the outcome, the
routine's ``on_end`` hooks run (routines use one to halt the robot). A routine that moves the
robot owns its motion for its whole run (``ctx.motion``, taken when it is started); a robot Stop
aborts it: its next move or ``check_cancelled`` raises ``RobotStopped`` and the job ends
``stopped`` with nothing stored.

A job that ends ``succeeded`` carries ``verdict_ok``: whether its result passed (a calibration's
``verdict.ok``, verify's ``passed``; None when the routine gives no verdict). A NOT OK verdict is
no failure of the job (the result is stored, to be looked at), but it is no success of the cell
either: ``cellctl job run --follow`` exits 3 for it. A job's end message says what happened first,
then what was done about it, and says the robot was stopped only when the routine had moved it.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from cellctl.errors import CellctlError
from cellctl.metrics import CellMetrics
from drivers.base import MotionSession, RobotBase, RobotStopped

log = logging.getLogger(__name__)

JobStateName = Literal["running", "succeeded", "failed", "cancelled", "stopped"]
MAX_FINISHED_JOBS = 200
MAX_RUNNING_JOBS = 4
"""Routines running at once in one service (each holds a thread and may hold a camera)."""


class JobCancelled(CellctlError):
    """Raised inside a routine when its job was cancelled."""


class InputTimedOut(JobCancelled):
    """An interactive step waited longer than its timeout: the job ends cancelled, saying so."""


class JobInputError(CellctlError, ValueError):
    """Operator input given to a job that is not waiting for it, or that is malformed."""


class TooManyJobs(CellctlError, RuntimeError):
    """``MAX_RUNNING_JOBS`` routines are running already."""


@dataclass
class Event:
    seq: int
    time_s: float
    kind: str
    """'progress', 'input_needed', 'state'."""
    data: dict[str, Any]


@dataclass
class Job:
    id: str
    name: str
    started_by: str
    params: dict[str, Any]
    state: JobStateName = "running"
    progress: float = 0.0
    message: str = "starting"
    result: dict[str, Any] | None = None
    error: str | None = None
    exception: BaseException | None = field(default=None, repr=False)
    """What ended a failed, stopped or cancelled job (typed, for callers that sort failures; not served)."""
    created_s: float = field(default_factory=time.time)
    finished_s: float | None = None
    events: list[Event] = field(default_factory=list)
    waiting_for: dict[str, Any] | None = None
    _cancel: threading.Event = field(default_factory=threading.Event)
    _inputs: queue.Queue[dict[str, Any]] = field(default_factory=queue.Queue)
    _changed: threading.Condition = field(default_factory=threading.Condition)

    def public(self) -> dict[str, Any]:
        return {
            "id": self.id, "name": self.name, "state": self.state, "progress": round(self.progress, 4),
            "message": self.message, "result": self.result, "error": self.error, "started_by": self.started_by,
            "params": self.params, "created_s": self.created_s, "finished_s": self.finished_s,
            "waiting_for": self.waiting_for, "events": len(self.events), "verdict_ok": self.verdict_ok,
        }

    @property
    def verdict_ok(self) -> bool | None:
        """Whether a succeeded job's result passed (None: still running, ended otherwise, or no verdict)."""
        return result_verdict_ok(self.result) if self.state == "succeeded" else None

    def _emit(self, kind: str, data: dict[str, Any]) -> None:
        with self._changed:
            self.events.append(Event(len(self.events), time.time(), kind, data))
            self._changed.notify_all()

    @property
    def closed(self) -> bool:
        """True once the job's last event, its end ``state``, is out: nothing follows it. (``state`` leaves
        ``running`` a moment earlier, while the end hooks run.)"""
        return bool(self.events) and self.events[-1].kind == "state"

    def events_after(self, seq: int, timeout_s: float) -> list[Event]:
        """Events with ``seq`` greater than the given one, waiting up to ``timeout_s`` for one."""
        with self._changed:
            if len(self.events) <= seq + 1 and not self.closed:
                self._changed.wait(timeout_s)
            return self.events[seq + 1 :]


class JobContext:
    """What a running routine sees of its job."""

    def __init__(self, job: Job, motion: MotionSession | None = None) -> None:
        self._job = job
        self.motion = motion
        """The robot motion this routine owns (taken when it was started), or None."""
        self.on_end: list[Callable[[], None]] = []
        self.moved = False
        """True once the routine has commanded a move (its end message then says the robot was stopped)."""

    @property
    def params(self) -> dict[str, Any]:
        return self._job.params

    @property
    def started_by(self) -> str:
        return self._job.started_by

    @property
    def name(self) -> str:
        """The routine's name (``verify``, ``jog-to-mark`` ...)."""
        return self._job.name

    def report(self, progress: float, message: str, **data: Any) -> None:
        job = self._job
        job.progress = max(0.0, min(1.0, progress))
        job.message = message
        log.info("job %s (%s): %.0f%% %s", job.id, job.name, job.progress * 100, message)
        job._emit("progress", {"progress": job.progress, "message": message, **data})

    def check_cancelled(self) -> None:
        """Raise ``JobCancelled`` once cancelled, ``RobotStopped`` once a Stop aborted the routine's motion."""
        if self.motion is not None:
            self.motion.check()
        if self._job._cancel.is_set():
            raise JobCancelled("cancelled on request")

    def sleep(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            self.check_cancelled()
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self._job._cancel.wait(min(left, 0.05))

    def wait_input(self, what: dict[str, Any], timeout_s: float = 3600.0) -> dict[str, Any]:
        """Announce what the routine needs from the operator and wait for it (cancellable)."""
        job = self._job
        job.waiting_for = what
        job._emit("input_needed", what)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                self.check_cancelled()
                try:
                    return job._inputs.get(timeout=0.1)
                except queue.Empty:
                    if time.monotonic() > deadline:  # an abandoned step cancels the job
                        raise InputTimedOut(f"no operator input within {timeout_s:.0f} s") from None
        finally:
            job.waiting_for = None


def result_verdict_ok(result: dict[str, Any] | None) -> bool | None:
    """A routine result's verdict: ``verdict.ok`` (calibrations), ``passed`` (verify); None: it has none."""
    if not isinstance(result, dict):
        return None
    verdict = result.get("verdict")
    if isinstance(verdict, dict) and isinstance(verdict.get("ok"), bool):
        return bool(verdict["ok"])
    passed = result.get("passed")
    return passed if isinstance(passed, bool) else None


def _not_ok_words(result: dict[str, Any]) -> str:
    verdict = result.get("verdict")
    if isinstance(verdict, dict):
        codes = [str(p.get("code")) for p in verdict.get("problems") or [] if isinstance(p, dict)]
        stored = f"stored as calibration {result['calibration_id']} (not activated); " if "calibration_id" in result \
            else ""
        return f"{', '.join(codes) or 'no problems listed'}; {stored}see the result's verdict for what to do"
    return "the check did not pass; see the result"


def _aftermath(ctx: JobContext) -> str:
    """What was done about a failed or cancelled routine: the robot only when the routine moved it."""
    if ctx.moved:
        return "the robot was stopped where it was and nothing was stored"
    return "the robot was not moved and nothing was stored"


class JobManager:
    """Starts routines in threads and keeps their jobs (the newest ``MAX_FINISHED_JOBS``)."""

    def __init__(self) -> None:
        self._jobs: dict[str, Job] = {}
        self._lock = threading.Lock()
        self._threads: dict[str, threading.Thread] = {}
        self.metrics: CellMetrics | None = None
        """Where finished jobs are counted (its ``Services``' metrics; None: nowhere)."""

    def start(self, name: str, fn: Callable[[JobContext], dict[str, Any]], params: dict[str, Any],
              started_by: str, motion: tuple[RobotBase, MotionSession] | None = None) -> Job:
        """Run ``fn`` in a thread; ``motion``: the robot and the motion session the job owns (it ends
        with the job). ``TooManyJobs`` when ``MAX_RUNNING_JOBS`` run already."""
        job = Job(id=uuid.uuid4().hex[:12], name=name, started_by=started_by, params=params)
        with self._lock:
            running = sum(1 for j in self._jobs.values() if j.state == "running")
            if running >= MAX_RUNNING_JOBS:
                raise TooManyJobs(f"{running} routines are running already (at most {MAX_RUNNING_JOBS}); "
                                  "wait for one to finish or cancel one")
            self._jobs[job.id] = job
            self._prune()
        thread = threading.Thread(target=self._run, args=(job, fn, motion), name=f"job-{name}-{job.id}",
                                  daemon=True)
        self._threads[job.id] = thread
        thread.start()
        return job

    def _run(self, job: Job, fn: Callable[[JobContext], dict[str, Any]],
             motion: tuple[RobotBase, MotionSession] | None) -> None:
        ctx = JobContext(job, motion[1] if motion is not None else None)
        try:
            result = fn(ctx)
            job.result = result
            job.state = "succeeded"
            job.progress = 1.0
            ok = result_verdict_ok(result)
            job.message = "done" if ok is not False else "done, but the verdict is NOT OK: " + _not_ok_words(result)
        except JobCancelled as exc:
            job.exception = exc
            job.state = "cancelled"
            if isinstance(exc, InputTimedOut):
                job.error = f"{exc}: the step was abandoned"
            job.message = f"{f'cancelled: {job.error}' if job.error else exc}; {_aftermath(ctx)}"
        except RobotStopped as exc:
            job.exception = exc
            job.state = "stopped"
            job.error = f"{exc}"
            job.message = "stopped by a robot Stop; nothing was stored (an engineer must resume the robot)"
        except Exception as exc:  # noqa: BLE001 - a routine's failure is reported, never raised into the server
            log.warning("job %s (%s) failed: %s", job.id, job.name, exc, exc_info=not isinstance(exc, ValueError))
            job.exception = exc
            job.state = "failed"
            job.error = f"{exc}"
            job.message = f"failed: {exc}; {_aftermath(ctx)}"
        finally:
            for hook in ctx.on_end:
                try:
                    hook()
                except Exception:  # noqa: BLE001 - every end hook runs
                    log.exception("job %s end hook failed", job.id)
            if motion is not None:
                motion[0].motion.end(motion[1])
            job.finished_s = time.time()
            if self.metrics is not None:
                self.metrics.routine_finished(job.name, job.state)
            job._emit("state", {"state": job.state, "message": job.message, "error": job.error})

    def _prune(self) -> None:
        finished = [j for j in self._jobs.values() if j.state != "running"]
        for j in sorted(finished, key=lambda j: j.created_s)[: max(0, len(finished) - MAX_FINISHED_JOBS)]:
            self._jobs.pop(j.id, None)
            self._threads.pop(j.id, None)

    def get(self, job_id: str) -> Job:
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise KeyError(f"no job {job_id!r} (finished jobs are kept for a while, then forgotten)")
        return job

    def list(self) -> list[Job]:
        with self._lock:
            return sorted(self._jobs.values(), key=lambda j: j.created_s, reverse=True)

    def cancel(self, job_id: str) -> Job:
        job = self.get(job_id)
        job._cancel.set()
        return job

    def give_input(self, job_id: str, data: dict[str, Any]) -> Job:
        job = self.get(job_id)
        if job.state != "running" or job.waiting_for is None:
            raise JobInputError(f"job {job_id} ({job.name}) is not waiting for input (state {job.state})")
        job._inputs.put(data)
        return job

    def join(self, job_id: str, timeout_s: float | None = None) -> Job:
        thread = self._threads.get(job_id)
        if thread is not None:
            thread.join(timeout_s)
        return self.get(job_id)

    def shutdown(self, timeout_s: float = 10.0) -> None:
        for job in self.list():
            if job.state == "running":
                job._cancel.set()
        for thread in list(self._threads.values()):
            thread.join(timeout_s)
