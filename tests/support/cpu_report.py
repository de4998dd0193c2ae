"""CPU seconds per test: a pytest plugin and its summary, for keeping ``tests/slow.txt`` true.

Wall times on the shared 2-core machine say more about the other sessions' load than about a test
(at a load of 20 a test's wall time was 10-16 times its CPU), so the slow list is measured in CPU:
this process's user + system time plus that of the children it waited for (``getrusage``), per test
phase (set-up, call, teardown), and each worker's collection. Children still running (a session's
served cell, a PostgreSQL cluster) are counted when they are reaped, not per test.

    CELLCTL_TEST_CPU_DIR=/tmp/cpu .venv/bin/python -m pytest -q -m "not slow" -p tests.support.cpu_report
    .venv/bin/python -m tests.support.cpu_report /tmp/cpu          # the summary, tests over 1 s of CPU

(``python -m pytest``: it puts the repository on ``sys.path`` before ``-p`` imports the plugin.)
Without ``CELLCTL_TEST_CPU_DIR`` the plugin records nothing. Each process (xdist worker) writes
``cpu-<worker>.jsonl`` there; its collection is counted from the plugin's import (after pytest's own).
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import pytest

ENV = "CELLCTL_TEST_CPU_DIR"


def cpu_s(children: bool = True) -> float:
    """User + system CPU seconds of this process and (``children``) of its reaped children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    if not children:
        return own.ru_utime + own.ru_stime
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    forked = sys.modules.get("tests.support.forked")  # the fork server's children: not ours to getrusage
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime + (forked.forked_cpu_s if forked else 0.0)


_START_CPU_S, _START_OWN_CPU_S = cpu_s(), cpu_s(children=False)
_out: list[IO[str]] = []


def _write(record: dict[str, Any]) -> None:
    folder = os.environ.get(ENV)
    if not folder:
        return
    if not _out:
        Path(folder).mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _out.append((Path(folder) / f"cpu-{worker}.jsonl").open("w"))
    _out[0].write(json.dumps(record) + "\n")
    _out[0].flush()


def pytest_collection_finish(session: pytest.Session) -> None:
    _write({"id": "COLLECTION", "phase": "collect", "cpu_s": cpu_s() - _START_CPU_S})


def _timed(item: pytest.Item, phase: str) -> Iterator[None]:
    cpu0, wall0 = cpu_s(), time.monotonic()
    yield
    _write({"id": item.nodeid, "phase": phase, "cpu_s": cpu_s() - cpu0, "wall_s": time.monotonic() - wall0})


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Iterator[None]:
    yield from _timed(item, "setup")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    yield from _timed(item, "call")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item) -> Iterator[None]:
    yield from _timed(item, "teardown")


def pytest_sessionfinish(session: pytest.Session) -> None:
    _write({"id": "TOTAL", "phase": "all", "cpu_s": cpu_s() - _START_CPU_S,
            "own_cpu_s": cpu_s(children=False) - _START_OWN_CPU_S})


def rows_of(path: Path) -> list[dict[str, Any]]:
    """The records of one process's file."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def summary(folder: Path, over_s: float = 1.0) -> str:
    """Collection and total CPU per worker, CPU of the tests, and the tests over ``over_s`` of CPU."""
    rows = [r for f in sorted(folder.glob("cpu-*.jsonl")) for r in rows_of(f)]
    if not rows:
        raise SystemExit(f"no cpu-*.jsonl in {folder}: run pytest with {ENV}={folder} -p tests.support.cpu_report")
    files = sorted(folder.glob("cpu-*.jsonl"))
    workers = [f for f in files if f.name != "cpu-main.jsonl"] or files  # -n 0: the main process alone
    ends = {f: [r for r in rows_of(f) if r["id"] in ("COLLECTION", "TOTAL")] for f in files}
    collect = [r["cpu_s"] for f in workers for r in ends[f] if r["id"] == "COLLECTION"]
    totals = [r["cpu_s"] for f in workers for r in ends[f] if r["id"] == "TOTAL"]
    # the controller's own CPU: its reaped children are the workers, already counted
    totals += [r.get("own_cpu_s", 0.0) for f in files if f not in workers for r in ends[f] if r["id"] == "TOTAL"]
    per_test: Counter[str] = Counter()
    for r in rows:
        if r["phase"] in ("setup", "call", "teardown"):
            per_test[r["id"]] += r["cpu_s"]
    lines = [f"workers: {len(workers)}; collection CPU s each: {', '.join(f'{c:.1f}' for c in collect)}",
             f"total CPU s (workers with their reaped children, and the controller): {sum(totals):.1f}",
             f"tests: {len(per_test)}, their CPU s: {sum(per_test.values()):.1f}",
             f"tests over {over_s} s of CPU:"]
    lines += [f"  {c:6.2f}  {name}" for name, c in per_test.most_common() if c > over_s]
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python -m tests.support.cpu_report FOLDER [OVER_S]")
    print(summary(Path(sys.argv[1]), float(sys.argv[2]) if len(sys.argv) == 3 else 1.0))
