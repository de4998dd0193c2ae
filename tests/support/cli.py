"""Run ``cellctl`` in the test process: the same ``main`` the console script calls, without a new
interpreter (a fresh ``cellctl`` pays seconds of imports and, on a cold cache, kernel compiles).

``run_cli`` answers like ``subprocess.run(..., capture_output=True, text=True)``: the exit code,
stdout and stderr as the process would have written them. What a process would print and exit on
(an uncaught exception) is printed as a traceback on stderr with exit code 1, so a test that checks
"no traceback" still sees one. Keep one subprocess test per command for the entry point itself.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
import sys
import traceback
from collections.abc import Iterator, Mapping
from pathlib import Path

from cellctl.cli import main


@contextlib.contextmanager
def _process_like(env: Mapping[str, str] | None, cwd: Path | None) -> Iterator[None]:
    """The environment, working directory and logging set-up a fresh process would have."""
    root = logging.getLogger()
    saved_handlers, saved_level = root.handlers[:], root.level
    saved_env = dict(os.environ)
    saved_cwd = os.getcwd()
    root.handlers.clear()  # main()'s basicConfig then writes to this call's stderr, as in a process
    try:
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        yield
    finally:
        for h in root.handlers:
            h.close()
        root.handlers[:] = saved_handlers
        root.setLevel(saved_level)
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)


def run_cli(*args: str, env: Mapping[str, str] | None = None,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS...`` in this process; ``env`` replaces the environment for the call."""
    out, err = io.StringIO(), io.StringIO()
    with _process_like(env, cwd), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:  # argparse's usage errors, --help
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except Exception:
            traceback.print_exc(file=err)
            code = 1
    return subprocess.CompletedProcess(["cellctl", *args], code, out.getvalue(), err.getvalue())


def run_process(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS...`` as its console script in a new process: for a command's one entry-point test."""
    cellctl = str(Path(sys.executable).with_name("cellctl"))
    return subprocess.run([cellctl, *args], capture_output=True, text=True, timeout=timeout_s)
