"""Where cellctl keeps its data by default (XDG base directories)."""

from __future__ import annotations

import os
from pathlib import Path


def data_dir() -> Path:
    """``$CELLCTL_DATA_DIR``, else ``$XDG_DATA_HOME/cellctl``, else ``~/.local/share/cellctl``."""
    explicit = os.environ.get("CELLCTL_DATA_DIR")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "cellctl"
