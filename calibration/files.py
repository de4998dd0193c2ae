"""Reading the files a user names (targets, cameras, poses, configs), with typed, actionable errors.

One way to turn "the file is missing / unreadable / not JSON / not YAML" into the caller's own
error type, with a message that names the file, says what it should have been and, for a parse
error, where (line and column). Used by ``calibration`` and by ``cellctl`` (its config and its
command line); the caller chooses the exception class, so each package keeps its own typed errors.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml


def read_text(path: str | Path, what: str, error: type[Exception]) -> str:
    """The text of ``path``; ``error("<path>: cannot read <what> (<reason>)")`` when it cannot be read.

    ``what`` names the file's role for the user, e.g. ``"the config file"``, ``"camera file"``.
    """
    p = Path(path)
    try:
        return p.read_text()
    except UnicodeDecodeError as exc:
        raise error(f"{p}: cannot read {what} (not a text file: {exc.reason} at byte {exc.start})") from exc
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from exc


def read_json(path: str | Path, what: str, error: type[Exception]) -> Any:
    """The parsed JSON of ``path``; ``error`` naming the file and the line when it is not JSON."""
    p = Path(path)
    text = read_text(p, what, error)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{p}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); "
                    f"expected {what}") from exc


def read_yaml(path: str | Path, what: str, error: type[Exception]) -> Any:
    """The parsed YAML of ``path`` (safe loader); ``error`` naming the file and the line when it is not YAML."""
    p = Path(path)
    text = read_text(p, what, error)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(f"{p}: not valid YAML ({yaml_error_text(exc)}); expected {what}") from exc


def yaml_error_text(exc: yaml.YAMLError) -> str:
    """A YAML error as ``line L, column C: problem`` (1-based), or its text when it has no position."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    if mark is None:
        return str(problem)
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
