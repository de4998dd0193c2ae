"""Shared output helpers of the CLI: JSON on stdout (and optionally to a file)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


class CommandError(Exception):
    """A command failed for a reason the user can fix; the message is printed as one line."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays (recursively) to plain Python for ``json``."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def dumps(result: Any) -> str:
    return json.dumps(to_jsonable(result), indent=2)


def emit(result: Any, out: str | Path | None = None) -> None:
    """Print ``result`` as JSON on stdout and, with ``out``, write the same JSON to that file."""
    text = dumps(result)
    if out:
        Path(out).write_text(text + "\n")
    sys.stdout.write(text + "\n")
    sys.stdout.flush()
