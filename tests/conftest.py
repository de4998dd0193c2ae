"""Fixtures shared by the whole suite: repo paths, test data, free ports, a served cellctl process.

It also marks every test by what it needs (``pytest -m "not slow"`` is the fast loop; see
docs/testing.md): ``unit`` (in-process, no peer), ``peer`` (a protocol peer on loopback: an
emulator, a fake camera, socat, PostgreSQL), ``e2e`` (a served ``cellctl`` process), ``browser``
(headless Chromium), and ``slow`` (over about 3 s on the 2-core reference machine: the measured
list in ``tests/slow.txt``, plus every browser test).
"""

from __future__ import annotations

import functools
import gc
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest

# Bytecode caches are written even when PYTHONDONTWRITEBYTECODE is set: without them every xdist worker
# compiles every module and pytest rewrites every test module's asserts again, which doubled the
# collection each worker pays (11.7 s of CPU instead of 5.1 s, docs/testing.md). They go to __pycache__
# (ignored by git), written atomically, and the served processes and CLI runs read them too.
sys.dont_write_bytecode = False


def keep_freed_memory() -> bool:
    """Has glibc's malloc keep what this process frees for its next allocations (``mallopt``): by default
    a freed block of over 128 KiB to 32 MiB goes back to the kernel (unmapped, or the heap's top trimmed)
    and the next image-sized array faults fresh zeroed pages in again, which was a fifth of a rendered pick
    scene's CPU (9 of 42 ms, 2,700 page faults) and most of the fast loop's system time (docs/testing.md).
    The test processes only: the served cells, peers and the fork server keep the allocator's defaults.
    False where the C library has no ``mallopt`` (not glibc)."""
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    return bool(mallopt(m_mmap_threshold, 32 << 20)) and bool(mallopt(m_trim_threshold, 1 << 30))


keep_freed_memory()

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
"""Real images and measurements copied into the repository, each folder with SOURCE.txt and LICENSE.txt."""


from tests.support.schedule import DEFAULT_S, DURATIONS, longest_units_first, read_durations  # noqa: E402
from tests.support.served import CELLCTL, Served, free_port, start_served, stop_served  # noqa: E402, F401


@pytest.fixture(scope="session")
def served_virtual_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """One ``cellctl serve`` of the built-in virtual cell for the session's read-only tests."""
    served = start_served(tmp_path_factory.mktemp("serve"))
    try:
        yield served
    finally:
        stop_served(served)


# -- parallel runs (pytest-xdist) ----------------------------------------------------------------------

WORKERS = 4
"""Workers for ``-n auto`` (pyproject's addopts): more than the 2 cores of the reference machine pay,
as much of the suite waits on motion and served processes rather than computing (docs/testing.md)."""
UR_GROUP = "ur_emulator"
"""The UR emulator listens on the fixed ports the ur_rtde client dials (30004, 29999, ...): its tests
share one xdist worker (``--dist loadgroup``), one emulator at a time."""
SHARED_CELLS = ("plc_cell", "served_virtual_cell")
"""Session fixtures that serve a cell: their tests share one worker, so the cell starts once."""
PG_GROUP = "postgres"
"""The store tests on the session's PostgreSQL cluster (``tests/store/conftest.py``): they share one worker,
so one cluster starts in a run, not one per worker (about 1 s of CPU each, and its server's)."""


NOT_UR = frozenset({"sim", "modbus", "replay"})
"""Robot adapters of the contract tests that need no UR emulator: their cases run on any worker."""


def _other_adapter(item: pytest.Item) -> bool:
    """A case of a UR module parametrized with another adapter (``[sim]``, ``[modbus]``, ``[replay]``)."""
    params = getattr(getattr(item, "callspec", None), "params", {})
    return any(isinstance(v, str) and v in NOT_UR for v in params.values())


def _on_session_postgres(item: pytest.Item, rel_path: str, fixturenames: set[str]) -> bool:
    """A store test that runs on the session's PostgreSQL cluster: it asks for it, or for its URL, or is the
    ``postgresql`` case of a backend parameter (``store_url``; a test may then ask for the cluster itself)."""
    if not rel_path.startswith("store/"):
        return False
    params = getattr(getattr(item, "callspec", None), "params", {})
    return bool(fixturenames & {"postgres", "postgres_url"}) or any(
        isinstance(v, str) and v == "postgresql" for v in params.values())


def xdist_group_of(item: pytest.Item, rel_path: str, module_text: str) -> str | None:
    """The worker group of a test under ``--dist loadgroup``, or None to balance it freely.

    The UR emulator's tests share one group (fixed ports; a UR module's cases of another robot adapter
    are balanced freely, their peers listen on free ports); the tests of a shared served cell share
    its group; the store tests on the session's PostgreSQL cluster share theirs (one cluster a run); a module
    with a module-scoped fixture (a served cell, a capture) stays on one worker
    so that the fixture runs once, not once per worker its tests land on.
    """
    if "ur_emulator" in module_text and not _other_adapter(item):
        return UR_GROUP
    names = set(getattr(item, "fixturenames", ()))
    for name in SHARED_CELLS:
        if name in names:
            return name
    if _on_session_postgres(item, rel_path, names):
        return PG_GROUP
    info = getattr(item, "_fixtureinfo", None)
    defs = info.name2fixturedefs.values() if info is not None else ()
    # (the thread check is module-scoped on every module: it does not pin a module to a worker)
    if any(d and d[-1].scope == "module" and d[-1].argname != "no_thread_left_behind" for d in defs):
        return rel_path
    return None


def group_of(item: pytest.Item) -> str:
    """The test's ``xdist_group`` as xdist names it (its marks' names sorted, joined by ``_``), or ""."""
    names = {str(m.args[0] if m.args else m.kwargs.get("name", "default")) for m in item.iter_markers("xdist_group")}
    return "_".join(sorted(names))


class XdistGroupIds:
    """Puts each test's ``xdist_group`` in its node id (``path::test@group``), which is how xdist's
    ``--dist loadgroup`` scheduler sees groups. xdist 3.8 does it by setting ``item._nodeid``, which
    pytest 9.2 no longer reads (a node id is ``item._id`` there), so without this no group held: a
    module's module-scoped cell started once per worker its tests landed on. Runs last; does nothing
    where xdist's own suffix is already there."""

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, config: pytest.Config, items: list[pytest.Item]) -> None:
        if not getattr(config.option, "loadgroup", False):
            return
        for item in items:
            group = group_of(item)
            if not group or item.nodeid.endswith("@" + group):
                continue
            if hasattr(item, "_id"):
                from _pytest.nodeid import NodeId  # pytest >= 9.2

                item._id = NodeId.parse(f"{item.nodeid}@{group}")
            else:
                setattr(item, "_nodeid", f"{item.nodeid}@{group}")  # noqa: B010 (xdist before pytest 9.2)


_pg_templates: list[str] = []


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(XdistGroupIds(), "cellctl-xdist-group-ids")
    if not hasattr(config, "workerinput"):  # the run's pytest process: one initdb for the run's PostgreSQL clusters
        from tests.store.pgcluster import TEMPLATE, make_template_dir

        if not os.environ.get(TEMPLATE):  # (a pytest run inside the suite's keeps the outer run's)
            _pg_templates.append(make_template_dir())
            os.environ[TEMPLATE] = _pg_templates[-1]


_shared_fork_server: list[Any] = []


def pytest_sessionstart(session: pytest.Session) -> None:
    """With xdist workers (started after this: their hook is ``trylast``), the run's one fork server
    (``tests/support/forked.py``), which they share: one server's imports instead of one per worker."""
    if session.config.pluginmanager.has_plugin("dsession"):
        from tests.support.forked import share_server

        process = share_server()
        if process is not None:
            _shared_fork_server.append(process)


def pytest_unconfigure(config: pytest.Config) -> None:
    from tests.support.forked import end_shared

    while _shared_fork_server:
        end_shared(_shared_fork_server.pop())
    if _pg_templates:
        from tests.store.pgcluster import TEMPLATE, remove_template_dir

        os.environ.pop(TEMPLATE, None)
        remove_template_dir(_pg_templates.pop())


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    """Moves what imports and collection made (modules, classes, the test items: a few million objects) out of
    the garbage collector's sight (``gc.freeze``): each full collection of a worker walked all of them again,
    about 2.4 s of its CPU in the fast loop (1.2 s after). Garbage made later is collected as before."""
    gc.collect()
    gc.freeze()


def fast_loop(markexpr: str) -> bool:
    """Whether ``-m`` leaves the slow tests out (the fast loop: ``-m "not slow"``, alone or with more)."""
    return "not slow" in " ".join(markexpr.split())


@pytest.hookimpl(optionalhook=True)  # xdist's hook: absent with -p no:xdist
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: ``CELLCTL_TEST_WORKERS`` if set, no workers for one file or one test (the run
    stays in this process and starts at once), one worker per core (at most ``WORKERS``) for the fast
    loop, which computes rather than waits, else ``WORKERS``."""
    if os.environ.get("CELLCTL_TEST_WORKERS"):
        return int(os.environ["CELLCTL_TEST_WORKERS"])
    paths = {a.split("::", 1)[0] for a in config.args}
    if len(paths) == 1 and Path(next(iter(paths))).is_file():
        return 0
    if fast_loop(str(config.getoption("markexpr", "") or "")):
        return max(1, min(WORKERS, len(os.sched_getaffinity(0))))
    return WORKERS


# -- threads with owners ---------------------------------------------------------------------------

THREAD_GRACE_S = 15.0
"""How long the check waits, in all, for threads still ending after a module's fixtures are gone (a
job's last step, a reader noticing its device closed): generous for a loaded CI machine."""
LIBRARY_THREADS: dict[str, str] = {
    "AnyIO worker thread": "anyio's worker threads (Starlette's run_in_threadpool, TestClient): anyio owns them "
                           "and ends the idle ones itself",
    "asyncio_": "asyncio's default executor of an event loop (a library's loop.run_in_executor(None, ...))",
    "ThreadPoolExecutor-": "an executor a library made without a name (pymodbus, asyncua, ...)",
    "Dummy-": "a thread started outside Python's threading (a C library's callback): nobody can join it",
    "render_": "drivers/sim/imaging/pool.py: the renderer's process-wide pool, bounded by the core count and reused "
               "by every render in the process (never one per call)",
    "pydevd": "a debugger's threads",
}
"""Threads a test may leave behind, by name prefix, and why (everything else is the product's or the
test's own, and must be joined by its owner)."""


def _left_behind(before: set[threading.Thread], grace_s: float) -> list[threading.Thread]:
    """Threads started since ``before`` that are still alive after a grace join (library threads excepted)."""
    deadline = time.monotonic() + grace_s
    left = []
    for t in threading.enumerate():
        if t in before or t is threading.current_thread() or t.name.startswith(tuple(LIBRARY_THREADS)):
            continue
        t.join(max(0.0, deadline - time.monotonic()))
        if t.is_alive():
            left.append(t)
    return left


def _describe_thread(t: threading.Thread) -> str:
    target = getattr(t, "_target", None)
    where = f"{getattr(target, '__module__', '?')}.{getattr(target, '__qualname__', '?')}" if target else \
        f"{type(t).__module__}.{type(t).__qualname__}.run"
    return f"{t.name!r} ({where}, daemon={t.daemon})"


@pytest.fixture(scope="module", autouse=True)
def no_thread_left_behind(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fails a module whose tests leave a thread running once every fixture of the module has been torn
    down (module scope: a module-scoped served cell keeps its threads until then, legitimately).
    Threads libraries own are named in ``LIBRARY_THREADS``; everything the product starts is joined
    by its owner on shutdown (docs/testing.md)."""
    before = set(threading.enumerate())
    yield
    left = _left_behind(before, THREAD_GRACE_S)
    if left:
        pytest.fail(f"{request.node.nodeid} left {len(left)} thread(s) running after its fixtures were torn down: "
                    + "; ".join(_describe_thread(t) for t in left)
                    + ". The product joins every thread it starts on shutdown (a test joins its own).", pytrace=False)


# -- markers ----------------------------------------------------------------------------------------

SLOW_LIST = Path(__file__).with_name("slow.txt")
E2E_HINTS = ("start_served(", "served_virtual_cell", "start_plc_cell(", "plc_cell", "uvicorn")
PEER_HINTS = ("PeerProcess", "netns", "postgres", "socat", "arv-fake", "ur_emulator", "Aravis",
              "pymodbus.client", "from asyncua")  # the last two: a PLC client against the cell's PLC servers
_module_text: dict[Path, str] = {}


def slow_tests(lines: Iterable[str]) -> set[str]:
    """Node ids of ``tests/slow.txt`` (one per line; ``#`` starts a comment)."""
    return {ln.split("#", 1)[0].strip() for ln in lines} - {""}


def kinds_of(rel_path: str, fixturenames: Iterable[str], module_text: str) -> set[str]:
    """The kind markers of a test from its path (relative to tests/), its fixtures and its module."""
    fixtures = set(fixturenames)
    if rel_path.startswith("ui/"):
        return {"browser", "e2e"}
    kinds = set()
    if rel_path == "test_readme.py" or any(h in module_text for h in E2E_HINTS) \
            or any(f.startswith(("served", "plc_cell")) for f in fixtures):
        kinds.add("e2e")
    if any(h in module_text for h in PEER_HINTS) or fixtures & {"ur_emulator", "postgres", "postgres_url"}:
        kinds.add("peer")
    return kinds or {"unit"}


@functools.cache
def _slow_list() -> frozenset[str]:
    return frozenset(slow_tests(SLOW_LIST.read_text().splitlines()) if SLOW_LIST.exists() else ())


def never_selected(markexpr: str, known: set[str]) -> bool:
    """Whether ``-m markexpr`` deselects every test that carries the markers ``known`` (and any others):
    the expression is false for every value of the other markers it names."""
    from itertools import product

    from _pytest.mark.expression import Expression

    try:
        expr = Expression.compile(markexpr)
    except Exception:  # noqa: BLE001 - pytest reports a bad expression itself
        return False
    names = sorted(set(markexpr.replace("(", " ").replace(")", " ").split()) - {"and", "or", "not"} - known)
    for values in product((False, True), repeat=len(names)):
        true = known | {name for name, value in zip(names, values, strict=True) if value}
        if expr.evaluate(lambda name, /, **kwargs: name in true):  # noqa: B023 - evaluated at once
            return False
    return True


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """A test file whose every test ``-m`` deselects is not imported at all: the fast loop (``-m "not slow"``)
    skips importing the page tests (Playwright) and the files listed whole in ``tests/slow.txt``, which each
    xdist worker would import only to deselect them (docs/testing.md, "The fast loop")."""
    markexpr = str(config.getoption("markexpr", "") or "")
    if not markexpr or collection_path.suffix != ".py" or not collection_path.name.startswith("test_"):
        return None
    root = Path(__file__).parent
    if not collection_path.is_relative_to(root):
        return None
    rel = collection_path.relative_to(root).as_posix()
    known = {"browser", "e2e", "slow"} if rel.startswith("ui/") else set()
    if not known and f"tests/{rel}" in _slow_list():
        known = {"slow"}
    return True if known and never_selected(markexpr, known) else None


@pytest.hookimpl(tryfirst=True)  # before xdist's worker reads the xdist_group marks (it runs first otherwise)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow = slow_tests(SLOW_LIST.read_text().splitlines()) if SLOW_LIST.exists() else set()
    root = Path(__file__).parent
    for item in items:
        path = Path(str(item.path))
        if path not in _module_text:
            _module_text[path] = path.read_text() if path.suffix == ".py" else ""
        rel = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        kinds = kinds_of(rel, getattr(item, "fixturenames", ()), _module_text[path])
        for kind in sorted(kinds):
            item.add_marker(kind)
        base_id, file_id = item.nodeid.split("[", 1)[0], item.nodeid.split("::", 1)[0]
        if "browser" in kinds or {item.nodeid, base_id, file_id} & slow:
            item.add_marker("slow")
        group = xdist_group_of(item, rel, _module_text[path])
        if group is not None and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(group))
    if getattr(config.option, "loadgroup", False):  # xdist's work order: the longest units first
        seconds = read_durations(DURATIONS.read_text().splitlines()) if DURATIONS.exists() else {}
        items[:] = longest_units_first(items, _work_unit, lambda item: seconds.get(item.nodeid, DEFAULT_S))


def _work_unit(item: pytest.Item) -> str:
    """What xdist hands a worker at once: the test's group, or the test alone."""
    group = group_of(item)
    return "@" + group if group else item.nodeid
