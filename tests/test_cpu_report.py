"""tests/support/cpu_report.py: the CPU each test costs, which keeps tests/slow.txt true."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.support.cpu_report import cpu_s, summary


def test_cpu_seconds_count_this_process_and_its_reaped_children() -> None:
    import subprocess
    import sys

    before = cpu_s()
    subprocess.run([sys.executable, "-c", "sum(i * i for i in range(3_000_000))"], check=True)
    assert cpu_s() - before > 0.05  # the child's work, counted once it was waited for


def test_summary_adds_the_phases_and_names_the_tests_over_the_limit(tmp_path: Path) -> None:
    rows = [{"id": "COLLECTION", "phase": "collect", "cpu_s": 5.0},
            {"id": "t.py::a", "phase": "setup", "cpu_s": 0.7, "wall_s": 1.0},
            {"id": "t.py::a", "phase": "call", "cpu_s": 0.6, "wall_s": 1.0},
            {"id": "t.py::b", "phase": "call", "cpu_s": 0.2, "wall_s": 9.0},
            {"id": "TOTAL", "phase": "all", "cpu_s": 7.5}]
    (tmp_path / "cpu-gw0.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    # the controller: its children are the workers (counted in their files), only its own CPU adds
    (tmp_path / "cpu-main.jsonl").write_text(json.dumps({"id": "TOTAL", "phase": "all", "cpu_s": 9.0,
                                                         "own_cpu_s": 1.5}) + "\n")
    text = summary(tmp_path, over_s=1.0)
    assert "workers: 1; collection CPU s each: 5.0" in text
    assert "total CPU s (workers with their reaped children, and the controller): 9.0" in text
    assert "tests: 2, their CPU s: 1.5" in text
    assert "1.30  t.py::a" in text and "t.py::b" not in text.split("over 1.0 s of CPU:")[1]


def test_an_empty_folder_says_how_to_fill_it(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="CELLCTL_TEST_CPU_DIR"):
        summary(tmp_path)
