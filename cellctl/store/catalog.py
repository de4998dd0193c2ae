"""The cell's backup folder, and a damaged store file set aside (with its robots' Stop latches read out).

``cellctl store backup`` without ``--out`` writes ``<backup dir>/<cell_id>-<UTC time>.db`` (or
``.json``); ``cellctl store backups`` lists them, newest first; ``cellctl store restore --latest``
takes the newest. The folder is ``store.backup_dir``, else ``<data dir>/backups`` (created 0700).
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellctl.store.errors import StoreError
from cellctl.store.files import SIDE_FILES, private_dir

if TYPE_CHECKING:
    from cellctl.config import CellConfig

SUFFIXES = {"sqlite": ".db", "json": ".json"}


def backup_dir(config: CellConfig) -> Path:
    if config.store.backup_dir:
        return Path(config.store.backup_dir).expanduser()
    from cellctl.paths import data_dir

    return data_dir() / "backups"


def _stamp(t_s: float) -> str:
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t_s))


def new_backup_path(config: CellConfig, fmt: str) -> Path:
    """A new file name in the backup folder (created 0700 when missing) for a backup made now."""
    folder = backup_dir(config)
    try:
        private_dir(folder)
    except OSError as exc:
        raise StoreError(f"backup: cannot create the backup folder {folder} ({exc.strerror}); "
                         "set store.backup_dir in the config or give --out") from None
    base = f"{config.cell_id}-{_stamp(time.time())}"
    out = folder / f"{base}{SUFFIXES[fmt]}"
    n = 2
    while out.exists():
        out = folder / f"{base}-{n}{SUFFIXES[fmt]}"
        n += 1
    return out


def list_backups(config: CellConfig) -> list[dict[str, Any]]:
    """This cell's backups in the backup folder, newest first (by modification time)."""
    folder = backup_dir(config)
    if not folder.is_dir():
        return []
    now = time.time()
    found = []
    for p in folder.iterdir():
        if p.name.startswith(f"{config.cell_id}-") and p.suffix in SUFFIXES.values() and p.is_file():
            st = p.stat()
            found.append({"file": str(p), "bytes": st.st_size, "modified_s": st.st_mtime,
                          "age_h": round((now - st.st_mtime) / 3600.0, 2)})
    return sorted(found, key=lambda b: (b["modified_s"], b["file"]), reverse=True)


def latest_backup(config: CellConfig) -> Path:
    backups = list_backups(config)
    if not backups:
        raise StoreError(f"restore --latest: no backups of cell {config.cell_id!r} in {backup_dir(config)}; "
                         "give the backup file with --from FILE")
    return Path(backups[0]["file"])


def set_aside(db: Path) -> Path:
    """Rename the SQLite file ``db`` and its side files to ``<db>.damaged-<UTC time>[-wal|-shm|...]``."""
    aside = db.with_name(f"{db.name}.damaged-{_stamp(time.time())}")
    n = 2
    while aside.exists():
        aside = db.with_name(f"{db.name}.damaged-{_stamp(time.time())}-{n}")
        n += 1
    for suffix in SIDE_FILES:
        side = db.with_name(db.name + suffix)
        if side.exists():
            side.rename(aside.with_name(aside.name + suffix))
    db.rename(aside)
    return aside


def read_latches(db: Path, cell_id: str) -> list[tuple[str, str, str, float]] | None:
    """The Stop latches stored in the (damaged) SQLite file ``db``: (robot_id, latched_by, reason,
    since_s); None when they cannot be read."""
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30)
    except sqlite3.Error:
        return None
    try:
        rows = conn.execute("SELECT robot_id, latched_by, reason, since_s FROM robot_latches WHERE cell_id = ? "
                            "ORDER BY robot_id", (cell_id,)).fetchall()
        return [(str(r[0]), str(r[1]), str(r[2]), float(r[3])) for r in rows]
    except (sqlite3.Error, ValueError, TypeError):
        return None
    finally:
        conn.close()
