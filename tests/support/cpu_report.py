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

Each test also gets its **process tree's** CPU (``phase: "tree"``, set-up to teardown): the worker and
every live descendant, read from ``/proc/<pid>/stat`` (user + system + the children each has waited
for) when the test starts and when it ends. So a module's served cell, a session's peer, the fork
server's children and Chromium (the Playwright driver's child) are charged to the test they work for
while it runs, not to whichever test reaps them. The fork server's children (forked ``cellctl`` runs and
peers; the server is shared by the run's workers) are counted by the process that asked for each
(``tests.support.forked.live``), with the whole CPU of those that ended (``forked_cpu_s``); the server
itself counts its own CPU only. A descendant that ends in between is counted by the
one that waited for it (ourselves, or a live descendant); one that leaves the tree (a daemon that
detaches, as ``pg_ctl start``'s server) is not seen. A reading lists ``/proc`` and reads the stat of
the tree's processes and of pids not seen before (about 1 ms per test).
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
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
_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")

Proc = tuple[int, int, int, int]
"""A process of ``/proc``: (parent pid, start time in ticks, CPU ticks: user + system of itself and of
the children it has waited for, CPU ticks of itself alone)."""



_OUTSIDE: set[int] = set()
"""Pids seen outside this process's tree: a process never moves into it later (only a reparenting to
init takes one out), so they are not read again (a pid reused by a new descendant within one run
would be missed: Linux hands pids out in order up to ``pid_max``, millions here)."""


def proc_table() -> dict[int, Proc]:
    """The :data:`Proc` of each process that may be in this process's tree, by pid (those that end while
    it reads are left out); what is found outside it is remembered and skipped next time."""
    table = {}
    for name in os.listdir("/proc"):
        if not name.isdigit() or int(name) in _OUTSIDE:
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                data = f.read()
        except OSError:
            continue
        rest = data[data.rindex(b")") + 2:].split()  # after "pid (comm) ": state ppid ... (man 5 proc)
        table[int(name)] = (int(rest[1]), int(rest[19]), sum(int(x) for x in rest[11:15]),
                            int(rest[11]) + int(rest[12]))
    return table


def tree_of(table: dict[int, Proc], root: int, forked: Iterable[int] = (), server: int = 0,
            ) -> dict[tuple[int, int], int]:
    """CPU ticks of ``root`` and each of its descendants, and of the ``forked`` runs this process asked the
    fork server for and theirs, keyed by (pid, start time) (pids are reused); the fork ``server`` counts
    its own CPU only (its children are all the test processes' forked runs when it is shared: each is
    counted through ``forked`` by the process that asked for it). The other pids of ``table`` join
    ``_OUTSIDE``."""
    kids: dict[int, list[int]] = {}
    for pid, (ppid, _, _, _) in table.items():
        kids.setdefault(ppid, []).append(pid)
    out, todo = {}, [root, *forked]
    while todo:
        pid = todo.pop()
        if pid in table:
            if pid == server:
                out[(pid, table[pid][1])] = table[pid][3]
                continue
            out[(pid, table[pid][1])] = table[pid][2]
            todo += kids.get(pid, [])
    _OUTSIDE.update(set(table) - {pid for pid, _ in out} - set(forked))
    return out


def tree_delta_s(before: dict[tuple[int, int], int], after: dict[tuple[int, int], int]) -> float:
    """CPU seconds the tree spent between two readings: what each process still there (or new) added,
    less what the ones that ended had before (their whole CPU now sits in their waiter's children's)."""
    ticks = sum(v - before.get(k, 0) for k, v in after.items()) - sum(v for k, v in before.items() if k not in after)
    return ticks * _TICK_S


_tree: list[tuple[dict[tuple[int, int], int], float]] = []


def _reading() -> tuple[dict[tuple[int, int], int], float]:
    """This process's tree with its live forked runs, and the CPU seconds of its forked runs that ended."""
    forked = sys.modules.get("tests.support.forked")
    if forked is None:
        return tree_of(proc_table(), os.getpid()), 0.0
    server = forked._server.server_pid if forked._server is not None else 0
    return tree_of(proc_table(), os.getpid(), set(forked.live), server), float(forked.forked_cpu_s)


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
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    """The test's process tree's CPU, set-up to teardown (the reading it ends with starts the next)."""
    if not os.environ.get(ENV):
        yield
        return
    if not _tree:
        _tree.append(_reading())
    yield
    after = _reading()
    ended_s = after[1] - _tree[0][1]  # forked runs that ended: their whole CPU, as the fork server reaped them
    _write({"id": item.nodeid, "phase": "tree", "cpu_s": tree_delta_s(_tree[0][0], after[0]) + ended_s})
    _tree[0] = after


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


def summary(folder: Path, over_s: float = 1.0, top: int = 30) -> str:
    """Collection and total CPU per worker, CPU of the tests, the tests over ``over_s`` of CPU, and the
    ``top`` tests and files by process-tree CPU."""
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
    tree: Counter[str] = Counter()
    for r in rows:
        if r["phase"] == "tree":
            tree[r["id"]] += r["cpu_s"]
    if tree:
        by_file: Counter[str] = Counter()
        for name, c in tree.items():
            by_file[name.split("::", 1)[0]] += c
        lines += [f"tests' process-tree CPU s (each test's worker and descendants, set-up to teardown): "
                  f"{sum(tree.values()):.1f}", f"the {top} dearest tests by process-tree CPU s:"]
        lines += [f"  {c:6.2f}  {name}" for name, c in tree.most_common(top)]
        lines += [f"the {top} dearest files by process-tree CPU s:"]
        lines += [f"  {c:6.2f}  {name}" for name, c in by_file.most_common(top)]
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python -m tests.support.cpu_report FOLDER [OVER_S]")
    print(summary(Path(sys.argv[1]), float(sys.argv[2]) if len(sys.argv) == 3 else 1.0))
