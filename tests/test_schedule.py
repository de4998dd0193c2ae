"""The order xdist hands out work (tests/support/schedule.py): the longest work units first."""

from __future__ import annotations

from tests.support.schedule import DEFAULT_S, DURATIONS, durations_from_report, longest_units_first, read_durations

REPORT = """\
============================ slowest durations =============================
217.35s call     tests/test_readme.py::test_the_tour_runs_as_written_twice_on_one_store
31.50s setup    tests/cellctl/test_routines_e2e.py::test_capture@cellctl/test_routines_e2e.py
3.90s call     tests/cellctl/test_routines_e2e.py::test_capture@cellctl/test_routines_e2e.py
0.20s teardown tests/cellctl/test_routines_e2e.py::test_capture@cellctl/test_routines_e2e.py
(12 durations < 0.005s hidden.)
"""


def test_a_report_sums_setup_call_and_teardown_per_test_without_the_group_suffix() -> None:
    got = durations_from_report(REPORT.splitlines())
    assert got == {"tests/test_readme.py::test_the_tour_runs_as_written_twice_on_one_store": 217.35,
                   "tests/cellctl/test_routines_e2e.py::test_capture": 35.6}


def test_units_go_longest_first_each_kept_together_in_its_own_order() -> None:
    items = ["a1", "b1", "a2", "c1", "b2", "d1"]  # unit = the letter
    seconds = {"a1": 1.0, "a2": 1.0, "b1": 0.5, "b2": 0.5, "c1": 5.0, "d1": 1.0}
    order = longest_units_first(items, lambda i: i[0], seconds.__getitem__)
    assert order == ["c1", "a1", "a2", "b1", "b2", "d1"]  # c 5 s, a 2 s, then b and d tie at 1 s: collection order


def test_the_durations_file_reads_and_its_ids_are_node_ids() -> None:
    seconds = read_durations(DURATIONS.read_text().splitlines())
    assert seconds and all(s >= 2 * DEFAULT_S for s in seconds.values())
    assert all(test_id.startswith("tests/") and "::" in test_id and "@" not in test_id for test_id in seconds)
