"""Start-up work: the compiled loops (numba) that frames, searches and calibrations run on, and the
plotting library of the calibration reports (matplotlib).

Loading them from numba's disk cache takes a second or two per process; compiling them on a cold
cache takes about a minute of CPU (renderer ~10 s, matcher ~20 s, calibration solver ~20 s on this
2-core machine, idle). Two users of this module:

- ``cellctl serve`` runs :func:`service_startup`'s tasks on one background thread as soon as its
  devices are open (numba compiles one function at a time anyway, so the order says what is ready
  first: the renderer, which the first ``GET /cameras/{id}/image`` needs, then the matcher, then
  the calibration solver). ``GET /health`` says ``starting`` with what it is ``waiting_for`` until
  they are done, then ``ok``; the service logs one line with the time it took. Requests are not
  refused meanwhile: a camera image waits (up to ``READY_WAIT_S``) for its camera's warm-up before
  the device deadline starts, and a search waits for the matcher's loops before its ``timeout_s``
  starts (``vision.shape.warm_up``); everything else is served at once.
- ``cellctl warm-up`` (run by ``deploy/setup.sh``) compiles everything into numba's disk cache, so
  a fresh clone's first frame, first search and first calibration load instead of compiling, and
  draws one report figure, which on a fresh machine builds matplotlib's font cache.

Where the compiled code is cached: beside each module (``__pycache__/*.nbi``, ``*.nbc``), or in
``NUMBA_CACHE_DIR`` when it is set (the systemd unit sets ``/var/lib/cellctl/numba-cache``, as
``/opt`` is read-only to the service). An edited module is compiled again (the cache is keyed by
the source file).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np

from cellctl.cell import Cell
from drivers.camera.sim import SimCamera

log = logging.getLogger(__name__)

RENDERER = "renderer kernels"
MATCHER = "matcher kernels"
CALIBRATION = "calibration kernels"
REPORT = "report plots"

READY_WAIT_S = 180.0
"""How long a request that needs a warm-up (a camera image) waits for it before answering 503
``starting``. On a warm cache the whole start-up takes 1-3 s; on a cold one the renderer alone is
~10 s of CPU, 25 s of wall time at a load of 18 on this 2-core machine and over 90 s at 30."""
STOP_JOIN_S = 120.0
"""At the service's stop the warm-up task in progress (loading or compiling compiled loops) finishes within this."""


def warm_renderer(cameras: Iterable[SimCamera] = ()) -> None:
    """Load the renderer's compiled loops; each given (open) simulated camera also inverts its lens."""
    from calibration.camera_model import CameraModel
    from drivers.sim.imaging import prepare

    cams = list(cameras)
    if not cams:
        prepare(CameraModel("opencv5", 16, 12, np.array([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]])))
    for cam in cams:
        cam.warm_up()


SEARCH_SIZE = (1280, 960)
"""Image size (width, height) the matcher's warm-up searches when no simulated camera tells it better."""


def warm_matcher(image_size: tuple[int, int] = SEARCH_SIZE) -> None:
    """Load the shape matcher's compiled loops (once per process), its warm-up search on an image of
    ``image_size`` (the cameras'), so that the first real search costs what the next ones do."""
    from vision.shape import warm_up

    warm_up(image_size)


_CALIBRATION_WARM = threading.Event()
_CALIBRATION_LOCK = threading.Lock()


def warm_calibration() -> None:
    """Load the camera calibration solver's compiled loops (once per process): a small synthetic
    calibration of each lens model (~0.2 s once loaded)."""
    if _CALIBRATION_WARM.is_set():
        return
    with _CALIBRATION_LOCK:
        if _CALIBRATION_WARM.is_set():
            return
        from numba.core.errors import NumbaPerformanceWarning

        from calibration.camera_model import CameraModel
        from calibration.intrinsics import calibrate
        from calibration.synthetic import plan_views, synthetic_detections
        from calibration.targets import Chessboard

        cam = CameraModel("opencv5", 640, 480, np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]))
        board = Chessboard(9, 6, 25.0)
        rng = np.random.default_rng(0)
        dets = synthetic_detections(cam, board, plan_views(cam, board, 6, rng), 0.1, rng)
        with warnings.catch_warnings():
            # compiling the Schur step says '@' is faster on contiguous arrays: known, and not the user's to act on
            warnings.simplefilter("ignore", NumbaPerformanceWarning)
            for model in ("opencv5", "opencv8", "division"):
                calibrate(dets, board, model)
        _CALIBRATION_WARM.set()


def warm_report() -> None:
    """Import matplotlib and draw one small report figure. On a fresh machine the first import builds
    matplotlib's font cache (in ``MPLCONFIGDIR``, default ``~/.cache/matplotlib``), which ``cellctl
    warm-up`` thereby does at set-up instead of the first calibration report; a process that calls it
    also has the plotting library loaded (1.4-2.9 s on this machine)."""
    from calibration.report import warm_up

    warm_up()


# -- the service's start-up ---------------------------------------------------------------------------


@dataclass
class _Task:
    name: str
    fn: Callable[[], None]
    done: threading.Event = field(default_factory=threading.Event)
    seconds: float | None = None
    error: str | None = None


class Startup:
    """Named start-up tasks run in order on one background thread; what is still pending, and
    waits for one of them. A task that fails is logged and counted as done (the first use of what
    it warms then pays the load itself): the service never stays ``starting`` for ever."""

    def __init__(self, tasks: Sequence[tuple[str, Callable[[], None]]], since_s: float | None = None) -> None:
        """``since_s``: the ``time.monotonic()`` the logged "ready in" counts from (default: now)."""
        self._tasks = [_Task(name, fn) for name, fn in tasks]
        self._t0 = time.monotonic() if since_s is None else since_s
        self.ready_after_s: float | None = None if self._tasks else 0.0
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()

    def start(self) -> None:
        """Run the tasks on a background thread (``stop`` joins it)."""
        self._thread = threading.Thread(target=self._run, name="cellctl-warm-up", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = STOP_JOIN_S) -> None:
        """The service stops: the tasks not started are skipped (counted done), the one running finishes;
        the thread is joined."""
        self._stopping.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("start-up: the warm-up thread did not end within %.0f s of the service's stop", timeout_s)

    def _run(self) -> None:
        for task in self._tasks:
            if self._stopping.is_set():
                task.error = "skipped: the service stopped first"
                task.seconds = 0.0
                task.done.set()
                continue
            t = time.monotonic()
            try:
                task.fn()
            except Exception as exc:  # noqa: BLE001 - reported; the first use will load what it needs itself
                task.error = f"{type(exc).__name__}: {exc}"
                log.warning("start-up: warming the %s failed; their first use loads them", task.name, exc_info=True)
            task.seconds = time.monotonic() - t
            if task is self._tasks[-1]:
                self.ready_after_s = time.monotonic() - self._t0  # before the last event: ready has a time
            task.done.set()
        parts = ", ".join(f"{t.name} {t.seconds:.1f} s" + (" (failed)" if t.error else "") for t in self._tasks)
        if self.ready_after_s is None:  # the service stopped before the last task ran
            log.info("service stopped before its warm-up was done (%s)", parts)
        else:
            log.info("service ready in %.1f s (%s)", self.ready_after_s, parts)

    @property
    def ready(self) -> bool:
        return all(t.done.is_set() for t in self._tasks)

    def waiting_for(self) -> list[str]:
        """The tasks not done yet, in the order they run."""
        return [t.name for t in self._tasks if not t.done.is_set()]

    def failed(self) -> dict[str, str]:
        return {t.name: t.error for t in self._tasks if t.error is not None}

    def wait(self, name: str, timeout_s: float) -> bool:
        """Wait until task ``name`` is done; True at once when there is no such task."""
        task = next((t for t in self._tasks if t.name == name), None)
        return task is None or task.done.wait(timeout_s)

    async def wait_async(self, name: str, timeout_s: float = READY_WAIT_S) -> bool:
        """:meth:`wait` without blocking the event loop (polls every 50 ms)."""
        task = next((t for t in self._tasks if t.name == name), None)
        if task is None:
            return True
        deadline = time.monotonic() + timeout_s
        while not task.done.is_set():
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(0.05)
        return True


def service_startup(cell: Cell, since_s: float | None = None) -> Startup:
    """The start-up work of a service on ``cell``: the renderer when it has a simulated camera
    (each open one also inverts its lens), the matcher and the calibration solver. Not matplotlib: its
    import (1-3 s of CPU) would be paid by every start, and only a report needs it."""
    sims = [slot for slot in cell.cameras.values() if isinstance(slot.device, SimCamera)]

    def renderer() -> None:  # with no sim camera open yet, the loops alone (its lens when it opens)
        warm_renderer([slot.device for slot in sims if slot.is_open and isinstance(slot.device, SimCamera)])

    def matcher() -> None:
        shown = [slot.device.settings() for slot in sims]  # a sim camera's size, no IO (None when closed)
        sizes = [(int(c["width"]), int(c["height"])) for c in shown if c.get("width") and c.get("height")]
        warm_matcher(max(sizes, key=lambda wh: wh[0] * wh[1]) if sizes else SEARCH_SIZE)

    tasks: list[tuple[str, Callable[[], None]]] = [(RENDERER, renderer)] if sims else []
    return Startup([*tasks, (MATCHER, matcher), (CALIBRATION, warm_calibration)], since_s)


_PARTS: dict[str, Callable[[], None]] = {MATCHER: warm_matcher, CALIBRATION: warm_calibration,
                                         RENDERER: warm_renderer, REPORT: warm_report}
"""What ``cellctl warm-up`` warms, the longest first on a cold cache (matcher ~20 s, solver ~20 s,
renderer ~10 s of CPU, report ~3 s): the order parallel jobs start them in."""


def _warm_part(name: str) -> float:
    """Warm one part; its seconds (rounded to 10 ms)."""
    t = time.monotonic()
    _PARTS[name]()
    return round(time.monotonic() - t, 2)


def warm_all(jobs: int = 1) -> dict[str, float]:
    """Compile (or load) every compiled loop of the renderer, matcher and calibration solver, and
    load the reports' plotting library; seconds per part. What ``cellctl warm-up`` runs.

    ``jobs`` 1 warms them in this process (they are then loaded here); more compiles each part in its
    own process, up to ``jobs`` at once, the longest first: on a cold cache the minute of CPU then takes
    about half of it on two cores. Those processes fill numba's disk cache and load nothing here.
    """
    if jobs <= 1:
        return {name: _warm_part(name) for name in _PARTS}
    with ProcessPoolExecutor(max_workers=min(jobs, len(_PARTS)), mp_context=get_context("spawn")) as pool:
        futures = {name: pool.submit(_warm_part, name) for name in _PARTS}
        return {name: f.result() for name, f in futures.items()}
