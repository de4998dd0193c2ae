"""``cellctl --version``, ``--help`` and the commands that talk to a running service start without the
heavy libraries: they import no numpy, OpenCV, numba or FastAPI (each costs tenths of a second to
seconds; ``cellctl --version`` took ~2 s when every command module was imported up front). Asserted on
imports in a fresh interpreter, not on time."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

HEAVY = ("numpy", "cv2", "numba", "fastapi", "scipy", "sqlalchemy", "pydantic")

_PROBE = """
import contextlib, io, sys
from cellctl.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        main(sys.argv[1:])
    except SystemExit:
        pass
print(" ".join(sorted(m for m in sys.modules if m.split(".")[0] in {heavy})))
"""


@pytest.mark.parametrize("argv", [
    ["--version"], ["--help"], ["job", "list", "--help"], ["job", "run", "verify", "--url", "http://127.0.0.1:9",
                                                          "--token", "t"],
    ["job", "list", "--url", "http://127.0.0.1:9", "--token", "t"],
    ["robot", "state", "--robot", "robot0", "--url", "http://127.0.0.1:9", "--token", "t"],
    ["robot", "move", "--robot", "robot0", "--named-pose", "home", "--url", "http://127.0.0.1:9", "--token", "t"],
])
def test_no_heavy_module_is_imported(argv: list[str]) -> None:
    probe = _PROBE.replace("{heavy}", repr(set(HEAVY)))
    r = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"cellctl {' '.join(argv)} imported: {r.stdout.strip()}"


def test_the_listed_help_is_each_command_s_own() -> None:
    """``cellctl --help`` lists the commands from a table (their modules are not imported); the table
    says what each module's own parser says."""
    from cellctl.cli import COMMANDS, build_parser

    full = build_parser()
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    assert {c.dest: c.help for c in sub._choices_actions} == {k: v[1] for k, v in COMMANDS.items()}
    lazy = build_parser(only="")
    assert lazy.format_help() == full.format_help()
