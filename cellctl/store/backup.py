"""Backup and restore of one cell's store.

Backup formats:

- ``sqlite`` (the default for a SQLite store): SQLite's online backup API copies the live database
  page by page into a new file while the service keeps running (readers and writers are not
  stopped); the copy is switched to a rollback journal so that it is one self-contained file,
  checked with ``PRAGMA integrity_check`` and renamed into place.
- ``json`` (the default for PostgreSQL): this cell's rows of every table, read in one
  repeatable-read snapshot, as a JSON document (:data:`DUMP_FORMAT`); other cells sharing the
  database are not included.

Restore reads either format (so a cell can move from its embedded SQLite file to the plant's
PostgreSQL database and back), checks it (format, schema version, cell id, columns), and then, in
**one** write transaction of the target store, deletes this cell's rows (only with ``force``; a
non-empty store is refused otherwise), inserts the backup's rows with their ids and logs a
``store.restore`` audit entry. A failure or a kill at any point leaves the store as it was.
When a row id of the backup is taken by another cell (moving a cell into a PostgreSQL database
that other cells already use), the cell's rows are renumbered in their original order, references
follow, and the renumbering is written into the restore's audit entry.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
from pathlib import Path
from typing import Any, Literal

import sqlalchemy as sa

import cellctl
from cellctl.store import schema as S
from cellctl.store.errors import RestoreRefused, StoreError, StoreFormatError
from cellctl.store.files import create_private, open_private
from cellctl.store.store import Store

DUMP_FORMAT = "cellctl-store-dump"
SQLITE_MAGIC = b"SQLite format 3\x00"
BackupFormat = Literal["sqlite", "json"]
INSERT_CHUNK = 500


def backup(store: Store, out: str | Path, fmt: BackupFormat | None = None) -> dict[str, Any]:
    """Write a backup of ``store`` (this cell) to ``out``; returns what was written."""
    out = Path(out)
    fmt = fmt or ("sqlite" if store.backend == "sqlite" else "json")
    if fmt == "sqlite" and store.backend != "sqlite":
        raise StoreError("backup: the sqlite format copies a SQLite store file; "
                         "a PostgreSQL store is backed up as json (--format json)")
    if out.is_dir():
        raise StoreError(f"backup: {out} is a directory; give a file name")
    if not out.parent.is_dir():
        raise StoreError(f"backup: the directory {out.parent} does not exist")
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    try:
        if fmt == "sqlite":
            counts = _sqlite_backup(Path(str(store.url.database)), tmp, store.cell_id)
        else:
            dump = dump_cell(store)
            counts = {name: len(t["rows"]) for name, t in dump["tables"].items()}
            with os.fdopen(open_private(tmp), "w") as f:
                json.dump(dump, f, separators=(",", ":"))
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(out.parent)
    return {"backend": store.backend, "store": store.describe(), "cell_id": store.cell_id, "format": fmt,
            "out": str(out), "bytes": out.stat().st_size, "counts": _held(counts)}


def _held(counts: dict[str, int]) -> dict[str, int]:
    """Rows per table, the tables that hold none of the cell's rows left out."""
    return {name: n for name, n in counts.items() if n}


def _sqlite_backup(db: Path, tmp: Path, cell_id: str) -> dict[str, int]:
    src = sqlite3.connect(db, timeout=30)
    try:
        create_private(tmp)  # 0600 before SQLite opens it (its journal gets the same mode)
        dst = sqlite3.connect(tmp)
        try:
            src.backup(dst)
            dst.execute("PRAGMA journal_mode=DELETE")
            check = dst.execute("PRAGMA integrity_check").fetchone()
            if check is None or check[0] != "ok":
                raise StoreError(f"backup: the copy of {db} fails its integrity check ({check}); "
                                 "the store itself may be damaged")
            counts = {t.name: int(dst.execute(f"SELECT count(*) FROM {t.name} WHERE cell_id = ?",  # noqa: S608
                                              (cell_id,)).fetchone()[0]) for t in S.CELL_TABLES}
        finally:
            dst.close()
    finally:
        src.close()
    with tmp.open("rb+") as f:
        os.fsync(f.fileno())
    return counts


def dump_cell(store: Store) -> dict[str, Any]:
    """This cell's rows of every table, from one consistent snapshot, as a JSON-able document."""
    tables: dict[str, Any] = {}
    with store.engine.connect() as conn:
        if store.backend == "postgresql":
            conn.execution_options(isolation_level="REPEATABLE READ")
        with conn.begin():
            for t in S.CELL_TABLES:
                cols = [c.name for c in t.columns]
                rows = conn.execute(sa.select(t).where(t.c.cell_id == store.cell_id).order_by(*S.order_of(t)))
                tables[t.name] = {"columns": cols, "rows": [list(r) for r in rows]}
    return {"format": DUMP_FORMAT, "schema_version": S.SCHEMA_VERSION, "cell_id": store.cell_id,
            "created_s": time.time(), "tool_version": cellctl.__version__, "source": store.describe(),
            "tables": tables}


def read_backup(path: str | Path, cell_id: str) -> dict[str, Any]:
    """Load and check a backup file of either format, as a dump document of ``cell_id``'s rows."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(len(SQLITE_MAGIC))
    except OSError as exc:
        raise RestoreRefused(f"restore: cannot read {path} ({exc.strerror})") from None
    dump = _read_sqlite_backup(path, cell_id) if head == SQLITE_MAGIC else _read_json_backup(path)
    _check_dump(dump, path, cell_id)
    return dump


def _read_sqlite_backup(path: Path, cell_id: str) -> dict[str, Any]:
    try:
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise RestoreRefused(f"restore: {path} cannot be opened as SQLite ({exc})") from None
    try:
        check = conn.execute("PRAGMA integrity_check").fetchone()
        if check is None or check[0] != "ok":
            raise RestoreRefused(f"restore: {path} fails SQLite's integrity check ({check}); use another backup")
        names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if S.meta.name not in names:
            raise RestoreRefused(f"restore: {path} is a SQLite file but not a cellctl store backup")
        meta = dict(conn.execute(f"SELECT key, value FROM {S.meta.name}").fetchall())  # noqa: S608
        cells = sorted({r[0] for t in S.CELL_TABLES if t.name in names
                        for r in conn.execute(f"SELECT DISTINCT cell_id FROM {t.name}")})  # noqa: S608
        if cells and cell_id not in cells:
            raise RestoreRefused(f"restore: {path} holds the store of cell(s) {', '.join(cells)}, not of "
                                 f"{cell_id!r}; use that cell's config or a backup of this cell")
        version = int(meta.get("schema_version", "0"))
        tables: dict[str, Any] = {}
        for t in S.CELL_TABLES:
            if t.name not in names:
                if S.TABLES_SINCE.get(t.name, 1) > version:
                    continue  # a backup of an older store: the table came later (restored empty)
                raise RestoreRefused(f"restore: {path} has no {t.name} table; not a complete cellctl store backup")
            order = ", ".join(c.name for c in S.order_of(t))
            cur = conn.execute(f"SELECT * FROM {t.name} WHERE cell_id = ? ORDER BY {order}",  # noqa: S608
                               (cell_id,))
            tables[t.name] = {"columns": [d[0] for d in cur.description], "rows": [list(r) for r in cur]}
    except sqlite3.Error as exc:
        raise RestoreRefused(f"restore: {path} cannot be read as a cellctl store backup ({exc})") from None
    finally:
        conn.close()
    if meta.get("format") != S.STORE_MARKER:
        raise RestoreRefused(f"restore: {path} is not a cellctl store backup (format={meta.get('format')!r})")
    return {"format": DUMP_FORMAT, "schema_version": version, "cell_id": cell_id, "tables": tables}


def _read_json_backup(path: Path) -> dict[str, Any]:
    try:
        dump = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RestoreRefused(f"restore: {path} is neither a SQLite store backup nor a JSON store dump "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
    if not isinstance(dump, dict) or dump.get("format") != DUMP_FORMAT:
        raise RestoreRefused(f"restore: {path} is JSON but not a cellctl store dump (no \"format\": \"{DUMP_FORMAT}\")")
    return dump


def _check_dump(dump: dict[str, Any], path: Path, cell_id: str) -> None:
    version = dump.get("schema_version")
    if not isinstance(version, int) or version < 1:
        raise RestoreRefused(f"restore: {path} has no valid schema_version")
    if version > S.SCHEMA_VERSION:
        raise StoreFormatError(f"restore: {path} has schema version {version}, newer than this cellctl "
                               f"supports ({S.SCHEMA_VERSION}); upgrade cellctl")
    if dump.get("cell_id") != cell_id:
        raise RestoreRefused(f"restore: {path} is a backup of cell {dump.get('cell_id')!r}, not of {cell_id!r}; "
                             "use that cell's config or a backup of this cell")
    tables = dump.get("tables")
    if not isinstance(tables, dict):
        raise RestoreRefused(f"restore: {path} has no tables")
    _upgrade(tables, version)
    for t in S.CELL_TABLES:
        entry = tables.get(t.name)
        want = [c.name for c in t.columns]
        if not isinstance(entry, dict) or entry.get("columns") != want or not isinstance(entry.get("rows"), list):
            raise RestoreRefused(f"restore: {path}: table {t.name} is missing or its columns differ from {want}")
        ci = want.index("cell_id")
        for row in entry["rows"]:
            if not isinstance(row, list) or len(row) != len(want) or row[ci] != cell_id:
                raise RestoreRefused(f"restore: {path}: table {t.name} has a malformed row or one of another cell")


def _upgrade(tables: dict[str, Any], version: int) -> None:
    """A backup of an older schema as this one's: the tables that came later empty, the columns that
    came later with the value the store's migration gives old rows (``schema.ADDED_COLUMNS``)."""
    for t in S.CELL_TABLES:
        if t.name not in tables and S.TABLES_SINCE.get(t.name, 1) > version:
            tables[t.name] = {"columns": [c.name for c in t.columns], "rows": []}
    for since, added in S.ADDED_COLUMNS.items():
        if since <= version:
            continue
        for table, column, default in added:
            entry = tables.get(table.name)
            if not isinstance(entry, dict) or not isinstance(entry.get("columns"), list) \
                    or column.name in entry["columns"] or not isinstance(entry.get("rows"), list):
                continue
            value = default.strip("'")
            entry["columns"] = [*entry["columns"], column.name]
            entry["rows"] = [[*r, value] if isinstance(r, list) else r for r in entry["rows"]]
            want = [c.name for c in table.columns]
            if sorted(entry["columns"]) == sorted(want):  # in the table's column order
                idx = [entry["columns"].index(n) for n in want]
                entry["columns"] = want
                entry["rows"] = [[r[i] for i in idx] if isinstance(r, list) and len(r) == len(idx) else r
                                 for r in entry["rows"]]


def restore(store: Store, src: str | Path, who: str, force: bool = False) -> dict[str, Any]:
    """Replace this cell's rows in ``store`` by those of the backup ``src``, atomically.

    Refused when the store already holds rows of this cell, unless ``force``. Row ids are kept
    unless another cell in the same database uses them (then renumbered, see the module docstring).
    """
    dump = read_backup(src, store.cell_id)
    counts = {t.name: len(dump["tables"][t.name]["rows"]) for t in S.CELL_TABLES}
    try:
        with store._write() as conn:
            existing = {t.name: int(conn.execute(sa.select(sa.func.count()).select_from(t).where(
                t.c.cell_id == store.cell_id)).scalar_one()) for t in S.CELL_TABLES}
            replaced = any(existing.values())
            if replaced and not force:
                what = ", ".join(f"{n} {name}" for name, n in existing.items() if n)
                raise RestoreRefused(f"restore: the store of cell {store.cell_id!r} is not empty ({what}); "
                                     "pass --force to replace it with the backup")
            for t in reversed(S.CELL_TABLES):
                conn.execute(t.delete().where(t.c.cell_id == store.cell_id))
            rows = {t.name: [dict(zip(dump["tables"][t.name]["columns"], r, strict=True))
                             for r in dump["tables"][t.name]["rows"]] for t in S.CELL_TABLES}
            remap = _ids_taken(conn, rows, store.cell_id)
            id_map, run_map = _insert_rows(conn, rows, remap)
            if store.backend == "postgresql":
                for t in S.CELL_TABLES:
                    if "id" in t.c:
                        _advance_sequence(conn, t)
            store._audit(conn, who, "store.restore", f"cell:{store.cell_id}",
                         {"from": str(Path(src).resolve()), "counts": counts, "replaced": existing if replaced else {},
                          "backup_created_s": dump.get("created_s"),
                          "calibration_ids_renumbered": {str(k): v for k, v in id_map.items()},
                          "run_ids_renumbered": {str(k): v for k, v in run_map.items()}}, "ok")
    except sa.exc.IntegrityError as exc:
        raise RestoreRefused(f"restore: the backup's rows violate the store's constraints "
                             f"({str(exc.orig).strip().splitlines()[0]}); nothing was changed") from None
    store.forget_doubt()  # the slot claims are the backup's now
    return {"backend": store.backend, "store": store.describe(), "cell_id": store.cell_id, "from": str(src),
            "counts": _held(counts), "replaced": replaced, "ids_renumbered": remap}


def _ids_taken(conn: sa.Connection, rows: dict[str, list[dict[str, Any]]], cell_id: str) -> bool:
    """Whether any of the backup's row ids is used by another cell (a database shared by cells)."""
    for t in S.CELL_TABLES:
        if "id" not in t.c:
            continue  # keyed by the cell id: no other cell's row can hold it
        ids = [r["id"] for r in rows[t.name]]
        for i in range(0, len(ids), INSERT_CHUNK):
            taken = conn.execute(sa.select(t.c.id).where(t.c.id.in_(ids[i:i + INSERT_CHUNK]),
                                                         t.c.cell_id != cell_id).limit(1)).scalar()
            if taken is not None:
                return True
    return False


def _insert_rows(conn: sa.Connection, rows: dict[str, list[dict[str, Any]]],
                 remap: bool) -> tuple[dict[int, int], dict[int, int]]:
    """Insert the backup's rows; with ``remap`` they get new ids (in their original order).

    Renumbering keeps every reference right: activations point at the new calibration ids, audit
    targets ``calibration:N`` are rewritten, cycles and slot claims follow their run (a cycle record
    keeps the run id it was written with: its kept failure frame is named by it); returns
    ``{old id: new id}`` of the calibrations and of the runs.
    """
    if not remap:
        for t in S.CELL_TABLES:
            for i in range(0, len(rows[t.name]), INSERT_CHUNK):
                conn.execute(t.insert(), rows[t.name][i:i + INSERT_CHUNK])
        return {}, {}
    cal_map: dict[int, int] = {}
    for r in rows[S.calibrations.name]:
        new_id = conn.execute(S.calibrations.insert().values({k: v for k, v in r.items() if k != "id"})
                              .returning(S.calibrations.c.id)).scalar_one()
        cal_map[int(r["id"])] = int(new_id)
    run_map: dict[int, int] = {}
    for r in rows[S.production_runs.name]:
        new_id = conn.execute(S.production_runs.insert().values({k: v for k, v in r.items() if k != "id"})
                              .returning(S.production_runs.c.id)).scalar_one()
        run_map[int(r["id"])] = int(new_id)
    for t in (S.production_cycles, S.production_slots, S.slot_claims):
        moved = []
        for r in rows[t.name]:
            r = {k: v for k, v in r.items() if k != "id"}
            if "run_id" in r:
                r["run_id"] = run_map.get(int(r["run_id"]), r["run_id"])
            moved.append(r)
        for i in range(0, len(moved), INSERT_CHUNK):
            conn.execute(t.insert(), moved[i:i + INSERT_CHUNK])
    drift = []
    for r in rows.get(S.drift_checks.name, []):
        r = {k: v for k, v in r.items() if k != "id"}
        if r.get("calibration_id") is not None:
            r["calibration_id"] = cal_map.get(int(r["calibration_id"]), r["calibration_id"])
        drift.append(r)
    for i in range(0, len(drift), INSERT_CHUNK):
        conn.execute(S.drift_checks.insert(), drift[i:i + INSERT_CHUNK])
    for t in (S.activations, S.recipes, S.audit):
        fixed = []
        for r in rows[t.name]:
            r = {k: v for k, v in r.items() if k != "id"}
            if t is S.activations and r["calibration_id"] is not None:
                if int(r["calibration_id"]) not in cal_map:
                    raise RestoreRefused(f"restore: an activation refers to calibration {r['calibration_id']}, "
                                         "which the backup does not hold; the backup is damaged")
                r["calibration_id"] = cal_map[int(r["calibration_id"])]
            if t is S.audit and str(r["target"]).startswith("calibration:"):
                old = str(r["target"]).split(":", 1)[1]
                if old.isdigit() and int(old) in cal_map:
                    r["target"] = f"calibration:{cal_map[int(old)]}"
            fixed.append(r)
        for i in range(0, len(fixed), INSERT_CHUNK):  # executemany keeps the order, so ids stay increasing
            conn.execute(t.insert(), fixed[i:i + INSERT_CHUNK])
    return cal_map, run_map


def _advance_sequence(conn: sa.Connection, table: sa.Table) -> None:
    """Move the id sequence past the restored ids; never backwards (other cells may be inserting)."""
    seq = conn.execute(sa.text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": table.name}).scalar_one()
    last = conn.execute(sa.text(f"SELECT last_value FROM {seq}")).scalar_one()  # noqa: S608 - name from the catalog
    top = conn.execute(sa.select(sa.func.max(table.c.id))).scalar()
    if top is not None and top > last:
        conn.execute(sa.text("SELECT setval(:s, :v)"), {"s": seq, "v": top})


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
