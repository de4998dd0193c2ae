"""The repository stands on its own: no tracked file points outside it to the planning folder.

A user who clones cellctl has no ``../shared`` (where the project's notes, interfaces and data
lived while it was planned); conventions and formats are in ``docs/``, test data in ``tests/data/``.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from tests.conftest import REPO

# Built from pieces so that this file does not match its own patterns.
_S = "shared"
PATTERNS = [
    re.compile(rf"\.\./{_S}\b"),
    re.compile(rf"/work/{_S}\b"),
    re.compile(rf"\b{_S}/(?:INTERFACES|FIELD_NOTES|DESIGN|STYLE)\.md"),
    re.compile(rf"\b{_S}/data\b"),
    re.compile(rf"[\"']{_S}[\"']\s*/\s*[\"']data[\"']"),  # Path(...) / "shared" / "data"
    re.compile(rf"\.parent\s*/\s*[\"']{_S}[\"']"),
]


def tracked_files() -> list[Path]:
    """The files git tracks (in a clone), or every file outside .venv/.git when there is no git checkout."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True, timeout=30)
        names = [n for n in out.stdout.decode().split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        names = [str(p.relative_to(REPO)) for p in REPO.rglob("*")
                 if p.is_file() and not {".venv", ".git"} & set(p.relative_to(REPO).parts)]
    return [REPO / n for n in names]


def offending_lines(path: Path) -> list[str]:
    try:
        text = path.read_text()
    except (UnicodeDecodeError, OSError):
        return []  # binary (images) or vanished
    return [f"{path.relative_to(REPO)}:{i}: {line.strip()}" for i, line in enumerate(text.splitlines(), 1)
            if any(p.search(line) for p in PATTERNS)]


def test_no_tracked_file_refers_to_the_planning_folder() -> None:
    files = tracked_files()
    assert len(files) > 100
    me = Path(__file__).resolve()
    found = [line for f in files if f.resolve() != me for line in offending_lines(f)]
    assert not found, "point these at docs/ or tests/data/ instead:\n" + "\n".join(found)


def test_the_patterns_catch_what_they_are_for(tmp_path: Path) -> None:
    bad = [f"see ../{_S}/INTERFACES.md", f"DATA = REPO.parent / \"{_S}\" / \"data\"", f"({_S}/FIELD_NOTES.md)",
           f"/work/{_S}/data/x", f"(real, {_S}/data)"]
    good = ["a shared 2-core machine", "shared memory", "Fixtures shared by the whole suite", "docs/conventions.md"]
    assert all(any(p.search(s) for p in PATTERNS) for s in bad)
    assert not any(p.search(s) for s in good for p in PATTERNS)
