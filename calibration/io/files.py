"""Reading the files a user names (targets, cameras, poses, configs), with typed, actionable errors.

One way to turn "the file is missing / unreadable / not JSON / not YAML" into the caller's own
error type, with a message that names the file, says what it should have been and, for a parse
error, where (line and column). Used by ``calibration`` and by ``cellctl`` (its config and its
command line); the caller chooses the exception class, so each package keeps its own typed errors.
"""

from __future__ import annotations

import json
from collections.abc import Callable
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
    return _parse(path, what, error, "JSON", json.loads, json.JSONDecodeError,
                  lambda e: f"line {e.lineno}, column {e.colno}: {e.msg}")


def read_yaml(path: str | Path, what: str, error: type[Exception]) -> Any:
    """The parsed YAML of ``path`` (safe loader); ``error`` naming the file and the line when it is not YAML."""
    return _parse(path, what, error, "YAML", yaml.safe_load, yaml.YAMLError, yaml_error_text)


def _parse(path: str | Path, what: str, error: type[Exception], language: str, parse: Callable[[str], Any],
           parse_error: type[Exception], where: Callable[[Any], str]) -> Any:
    text = read_text(path, what, error)
    try:
        return parse(text)
    except parse_error as exc:
        raise error(f"{Path(path)}: not valid {language} ({where(exc)}); expected {what}") from exc


def yaml_error_text(exc: yaml.YAMLError) -> str:
    """A YAML error in one line that names where it is: ``line L, column C: what`` (1-based).

    When the problem's context starts elsewhere (an unclosed bracket), that line is named too.
    """
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    what = str(getattr(exc, "problem", None) or str(exc).splitlines()[0])
    context = getattr(exc, "context", None)
    context_mark = getattr(exc, "context_mark", None)
    if context and context_mark is not None and context_mark is not mark:
        what = f"{what} ({context} that starts on line {context_mark.line + 1})"
    if mark is None:
        return what
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}"
