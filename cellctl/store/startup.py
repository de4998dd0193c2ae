"""What ``cellctl serve`` checks about the store before it serves anything.

A truncated copy, a deleted file or an unmounted disk must not look like "no calibrations". So the
service records, at every start that passed these checks, that the cell has run on a store: the
marker ``<data dir>/<cell_id>.store-started.json`` (mode 0600) names the store, its size and its
row counts. At the next start:

- a SQLite store that is missing or 0 bytes while the marker exists, or a store that holds no row
  of the cell while it held some at the last start, refuses the start: the message says what was
  expected, what was found, how to restore the last backup and how to begin a new store on purpose
  (``cellctl serve --new-store``, or deleting the marker);
- a SQLite file that fails ``PRAGMA quick_check`` refuses the start (restore the last backup);
- with no marker (the first start ever) a missing store is created silently.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellctl.store.errors import StoreDamaged, StoreUnavailable
from cellctl.store.files import open_private, private_dir
from cellctl.store.integrity import quick_check, restore_commands

if TYPE_CHECKING:
    from cellctl.config import CellConfig


class StoreStartRefused(StoreUnavailable):
    """The store is not the one the cell ran on before (missing, empty, wiped): the service does not start."""


def marker_path(config: CellConfig) -> Path:
    from cellctl.paths import data_dir

    return data_dir() / f"{config.cell_id}.store-started.json"


def read_marker(path: Path) -> dict[str, Any] | None:
    """The marker's content; None when there is none; ``{}`` when it exists but cannot be read
    (the cell has still run before)."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


ROW_WORDS = {"calibrations": "calibrations", "activations": "activations", "recipes": "recipe versions",
             "audit": "audit entries"}


def _rows(counts: dict[str, int]) -> str:
    shown = [f"{n} {ROW_WORDS.get(name, name)}" for name, n in counts.items() if n]
    return ", ".join(shown) if shown else "no rows"


def _refusal(config: CellConfig, marker: dict[str, Any], marker_file: Path, found: str) -> StoreStartRefused:
    when = marker.get("started_utc", "an earlier start")
    before = f"{marker.get('store', 'its store')}"
    if isinstance(marker.get("bytes"), int):
        before += f", {marker['bytes']} bytes"
    if isinstance(marker.get("counts"), dict):
        before += f", {_rows(marker['counts'])}"
    return StoreStartRefused(
        f"refusing to start: {found}, but cell {config.cell_id!r} ran on a store before (at {when}: {before}; "
        f"recorded in {marker_file}); starting would serve an empty store (no calibrations, no recipes). "
        f"Restore the last backup: {restore_commands(config.source)}; or, to begin a new empty store on "
        f"purpose, start once with cellctl serve --config {config.source or 'cell.yaml'} --new-store "
        f"(or delete {marker_file})")


def check_store_at_start(config: CellConfig, new_store: bool = False) -> dict[str, Any]:
    """Check the store as described in the module docstring, then record this start in the marker.

    Raises :class:`StoreStartRefused`, :class:`StoreDamaged` or :class:`StoreUnavailable` (messages
    say what to do); returns what was checked.
    """
    from cellctl.store import Store, store_url
    from cellctl.store.backends import backend_of
    from cellctl.store.integrity import recovery_hint

    url = store_url(config)
    mark_file = marker_path(config)
    marker = None if new_store else read_marker(mark_file)
    db = Path(str(url.database)) if backend_of(url) == "sqlite" else None
    if db is not None:
        if marker is not None and not db.exists():
            raise _refusal(config, marker, mark_file, f"the store {db} does not exist")
        if marker is not None and db.stat().st_size == 0:
            raise _refusal(config, marker, mark_file, f"the store {db} is empty (0 bytes)")
        problem = quick_check(db) if db.exists() and db.stat().st_size > 0 else None
        if problem is not None:
            raise StoreDamaged(f"refusing to start: the store {db} is damaged ({problem}); restore the last "
                               f"backup: {restore_commands(config.source)}")
    with Store(url, config.cell_id, recovery_hint(config.source)) as store:
        counts = store.counts()
        described = store.describe()
    before = marker.get("counts") if marker else None
    if isinstance(before, dict) and any(before.values()) and not any(counts.values()):
        raise _refusal(config, marker or {}, mark_file, f"the store {described} holds no rows of the cell")
    record = {"cell_id": config.cell_id, "store": described, "started_utc": time.strftime(
        "%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "bytes": db.stat().st_size if db is not None else None,
        "counts": counts}
    _write_marker(mark_file, record)
    return {**record, "first_start": marker is None, "marker": str(mark_file)}


def _write_marker(path: Path, record: dict[str, Any]) -> None:
    """Replace the marker atomically (a new 0600 file renamed over it)."""
    private_dir(path.parent)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        with os.fdopen(open_private(tmp), "w") as f:
            json.dump(record, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
