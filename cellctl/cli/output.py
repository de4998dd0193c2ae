"""Shared output helpers of the CLI: JSON on stdout (and optionally to a file)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from cellctl.errors import CellctlError


class CommandError(CellctlError):
    """A command failed for a reason the user can fix; the message is printed as one line."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def dumps(result: Any) -> str:
    """The command's JSON: numpy values as plain numbers; a NaN/infinity is an error naming its key."""
    if "numpy" not in sys.modules:  # a service's answer (plain JSON values): no numpy to load for it
        try:
            return json.dumps(result, indent=2, allow_nan=False)
        except ValueError:
            pass  # a NaN or infinity: the strict writer below names its key
    from calibration import io as cal_io  # here, not at the top: `cellctl job list` loads no numpy

    return cal_io.dumps(result, indent=2)


def emit(result: Any, out: str | Path | None = None) -> None:
    """Print ``result`` as JSON on stdout and, with ``out``, write the same JSON to that file."""
    text = dumps(result)
    if out:
        Path(out).write_text(text + "\n")
    sys.stdout.write(text + "\n")
    sys.stdout.flush()
