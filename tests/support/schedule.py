"""The order xdist hands out work: the longest work units first (longest-processing-time first).

Under ``--dist loadgroup`` a work unit is a test's ``xdist_group`` (a shared served cell, the UR
emulator's tests, a module with a module-scoped fixture) or, for a test in none, the test alone; a
worker pulls the next unit when it runs dry. xdist queues the units in the order they first appear in
the collection (``--no-loadscope-reorder``; its own reorder sorts by the number of tests, which put the
two README tours, single tests of minutes, behind hundreds of millisecond tests and made them the run's
tail). Ordering the collection by each unit's measured seconds, longest first, keeps a long unit from
starting last while the other workers sit idle.

The seconds come from ``tests/durations.txt`` (setup + call + teardown per test, from a whole run's
``--durations=0``; see docs/testing.md); a test not listed counts ``DEFAULT_S``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TypeVar

DURATIONS = Path(__file__).resolve().parents[1] / "durations.txt"
DEFAULT_S = 0.3
"""Seconds of a test absent from the durations file (the median test of the suite takes less)."""

_DURATION_LINE = re.compile(r"^\s*(?P<s>\d+(?:\.\d+)?)s\s+(?:setup|call|teardown)\s+(?P<id>\S+)")

Item = TypeVar("Item")


def read_durations(lines: Iterable[str]) -> dict[str, float]:
    """Seconds per test id from lines ``<seconds> <node id>`` (``#`` starts a comment)."""
    seconds: dict[str, float] = {}
    for line in lines:
        text = line.split("#", 1)[0].split()
        if len(text) == 2:
            seconds[text[1]] = float(text[0])
    return seconds


def durations_from_report(lines: Iterable[str]) -> dict[str, float]:
    """Seconds per test id (setup + call + teardown summed) from pytest's ``--durations=0`` lines;
    an xdist group suffix (``@group``) is dropped, so the ids match the collection's."""
    seconds: dict[str, float] = {}
    for line in lines:
        m = _DURATION_LINE.match(line)
        if m:
            test_id = m["id"].split("@", 1)[0]
            seconds[test_id] = seconds.get(test_id, 0.0) + float(m["s"])
    return seconds


def longest_units_first(items: Sequence[Item], unit_of: Callable[[Item], str],
                        seconds_of: Callable[[Item], float]) -> list[Item]:
    """``items`` with each work unit's tests together, the units ordered by their summed seconds,
    longest first (ties in collection order); the order inside a unit is kept."""
    units: dict[str, list[Item]] = {}
    for item in items:
        units.setdefault(unit_of(item), []).append(item)
    weight = {unit: sum(seconds_of(i) for i in members) for unit, members in units.items()}
    order = sorted(units, key=lambda unit: -weight[unit])  # sorted() is stable: ties keep collection order
    return [item for unit in order for item in units[unit]]


if __name__ == "__main__":  # refresh: pytest -q --durations=0 | python -m tests.support.schedule
    import sys

    measured = durations_from_report(sys.stdin)
    print("# Seconds per test (setup + call + teardown) from a whole run's `pytest -q --durations=0`;")
    print("# tests/support/schedule.py orders xdist's work by them. Regenerate: see docs/testing.md.")
    for test_id, s in sorted(measured.items(), key=lambda kv: -kv[1]):
        if s >= 2 * DEFAULT_S:
            print(f"{s:.2f} {test_id}")
