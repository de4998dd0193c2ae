"""``cellctl store backup|backups|restore|info|add``: back up and restore the cell's store; add a calibration file.

``add`` stores a calibration file made elsewhere (cam.json, he.json, np.json) as a new, inactive
version, checked as ``POST /calibrations`` checks it (``cellctl.calibration_file``).

A SQLite store is backed up with SQLite's online backup API (the service may keep running); a
PostgreSQL store as a JSON dump of this cell's rows. Without ``--out`` a backup goes to the cell's
backup folder (catalog.py), which ``backups`` lists. Restore reads either format, refuses to
overwrite a non-empty store unless ``--force``, and replaces the cell's rows in one transaction;
a damaged SQLite file is set aside (``--force``) and the backup restored into a new one.
"""

from __future__ import annotations

import argparse
import getpass
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellctl.cli.output import CommandError

if TYPE_CHECKING:
    from cellctl.config import CellConfig


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "store", help="back up / restore the calibration, recipe and audit store",
        description="Back up and restore the cell's store (calibrations, activations, recipes, audit log).")
    ssub = p.add_subparsers(dest="store_command", metavar="ACTION", required=True)

    b = ssub.add_parser("backup", help="write a backup of this cell's store to a file",
                        description="SQLite: an online copy of the database file (sqlite format); "
                                    "PostgreSQL: a JSON dump of this cell's rows (json format).")
    b.add_argument("--config", required=True, help="cell.yaml naming the store (store.url / store.path)")
    b.add_argument("--out", help="the backup file to write (replaced atomically); default: a new file "
                                 "<cell_id>-<UTC time>.db|.json in store.backup_dir (default <data dir>/backups)")
    b.add_argument("--format", choices=("sqlite", "json"), default=None,
                   help="sqlite (default for a SQLite store) or json (default for PostgreSQL; works for both)")
    b.set_defaults(func=run_backup)

    r = ssub.add_parser("restore", help="restore this cell's store from a backup file",
                        description="Reads a sqlite or json backup, refuses a non-empty store unless --force, "
                                    "and replaces the cell's rows in one transaction (all or nothing).")
    r.add_argument("--config", required=True, help="cell.yaml naming the store (store.url / store.path)")
    which = r.add_mutually_exclusive_group(required=True)
    which.add_argument("--from", dest="src", help="the backup file (from cellctl store backup)")
    which.add_argument("--latest", action="store_true", help="the newest backup in the backup folder "
                                                             "(see cellctl store backups)")
    r.add_argument("--force", action="store_true", help="replace a store that already holds rows of this cell; "
                                                        "a damaged SQLite store file is renamed <file>.damaged-<time>")
    r.add_argument("--who", default=None, help="name logged in the audit entry (default: cli:<user>)")
    r.set_defaults(func=run_restore)

    ls = ssub.add_parser("backups", help="this cell's backups in the backup folder, newest first")
    ls.add_argument("--config", required=True, help="cell.yaml (store.backup_dir, default <data dir>/backups)")
    ls.set_defaults(func=run_backups)

    a = ssub.add_parser("add", help="store a calibration file (cam.json, he.json, np.json) as a new, inactive version",
                        description="Checks the file as POST /calibrations does (kind, values, finite numbers) and "
                                    "stores it as a new version of its camera (and robot); it is not activated "
                                    "(POST /calibrations/{id}/activate, or the page's Calibrations tab). Works on "
                                    "the store named by the config; a running service sees it at once.")
    a.add_argument("file", help="the calibration file: cam.json (calib intrinsics, calib import, calib dlt), he.json "
                                "(calib handeye, --dof 4 too) or np.json (calib npoint)")
    a.add_argument("--config", required=True, help="cell.yaml naming the store and the cell's cameras and robots")
    a.add_argument("--kind", choices=("camera", "handeye", "npoint", "conveyor"), default=None,
                   help="the calibration's kind (default: recognised from the file's keys)")
    a.add_argument("--camera", default=None, help="the camera it belongs to (default: the config's calibration.camera)")
    a.add_argument("--robot", default=None, help="hand-eye and n-point: the robot (default: calibration.robot)")
    a.add_argument("--note", default="", help="a note stored with the version")
    a.add_argument("--who", default=None, help="name logged as its creator (default: cli:<user>)")
    a.set_defaults(func=run_add)

    i = ssub.add_parser("info", help="where the store is, whether SQLite finds it sound, how many rows this cell has")
    i.add_argument("--config", required=True)
    i.set_defaults(func=run_info)


@contextmanager
def _store_errors() -> Iterator[None]:
    import sqlalchemy as sa

    try:
        yield
    except sa.exc.SQLAlchemyError as exc:
        text = str(getattr(exc, "orig", None) or exc).strip().splitlines()
        raise CommandError(f"store: {text[0] if text else type(exc).__name__}") from None


def _with_store(args: argparse.Namespace, fn: Callable[[CellConfig, Any], dict[str, Any]],
                must_exist: bool) -> dict[str, Any]:
    from cellctl.config import load_config
    from cellctl.store import Store, store_url
    from cellctl.store.backends import backend_of
    from cellctl.store.integrity import recovery_hint

    cfg = load_config(args.config)
    with _store_errors():
        url = store_url(cfg)
        if must_exist and backend_of(url) == "sqlite" and not Path(str(url.database)).exists():
            raise CommandError(f"no store at {url.database} for cell {cfg.cell_id!r}; nothing to back up "
                               "(check store.path in the config)")
        with Store(url, cfg.cell_id, recovery_hint(cfg.source)) as store:
            return fn(cfg, store)


def _sqlite_file(cfg: CellConfig) -> Path | None:
    """The store's SQLite file when it is one and holds something (None: PostgreSQL, missing or empty)."""
    from cellctl.store import store_url
    from cellctl.store.backends import backend_of

    url = store_url(cfg)
    db = Path(str(url.database))
    return db if backend_of(url) == "sqlite" and db.is_file() and db.stat().st_size > 0 else None


def run_backup(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.store.backup import BackupFormat, backup
    from cellctl.store.catalog import new_backup_path

    def go(cfg: CellConfig, store: Any) -> dict[str, Any]:
        fmt: BackupFormat = args.format or ("sqlite" if store.backend == "sqlite" else "json")
        return backup(store, args.out or new_backup_path(cfg, fmt), fmt)

    return _with_store(args, go, must_exist=True)


def run_backups(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.config import load_config
    from cellctl.store.catalog import backup_dir, list_backups

    cfg = load_config(args.config)
    return {"cell_id": cfg.cell_id, "dir": str(backup_dir(cfg)), "backups": list_backups(cfg)}


def run_restore(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.config import load_config
    from cellctl.store.backup import restore
    from cellctl.store.catalog import latest_backup, read_latches, set_aside
    from cellctl.store.integrity import quick_check

    cfg = load_config(args.config)
    with _store_errors():
        src = latest_backup(cfg) if args.latest else Path(args.src)
    if not src.is_file():
        raise CommandError(f"--from {src}: no such file; give a file written by cellctl store backup")
    who = args.who or f"cli:{getpass.getuser()}"
    aside: Path | None = None
    db = _sqlite_file(cfg)
    problem = quick_check(db) if db is not None else None
    latches: list[tuple[str, str, str, float]] | None = []
    if db is not None and problem is not None:
        if not args.force:
            raise CommandError(f"the store {db} is damaged ({problem}); with --force it is renamed "
                               f"{db.name}.damaged-<time> and the backup is restored into a new store")
        latches = read_latches(db, cfg.cell_id)
        aside = set_aside(db)

    def go(_cfg: CellConfig, store: Any) -> dict[str, Any]:
        out = restore(store, src, who, force=args.force)
        for robot_id, by, reason, since_s in latches or []:  # a latched robot stays latched (docs/store.md)
            store.set_latch(robot_id, by, reason, since_s, result=f"carried over from the damaged store {aside}")
        return out

    out = _with_store(args, go, must_exist=False)
    if aside is None:
        return out
    if latches is None:
        print(f"cellctl: the Stop latches stored in {aside} cannot be read: no robot is latched now; check "
              "every robot before it moves again", file=sys.stderr)
    return {**out, "damaged_store_set_aside": str(aside),
            "latches_carried_over": None if latches is None else [r[0] for r in latches]}


def run_info(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.config import load_config
    from cellctl.store.integrity import quick_check, recovery_hint

    db = _sqlite_file(load_config(args.config))
    problem = quick_check(db) if db is not None else None
    if problem is not None:
        raise CommandError(f"the store {db} is damaged ({problem}); {recovery_hint(args.config)}")
    return _with_store(args, lambda _cfg, store: {
        "backend": store.backend, "store": store.describe(), "cell_id": store.cell_id,
        "integrity": "ok" if db is not None else "not checked", "counts": store.counts()}, must_exist=False)


def run_add(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.io import read_json
    from cellctl.calibration_file import CalibrationFileError, add_calibration

    if len(args.note) > 500:
        raise CommandError("--note: at most 500 characters")
    data = read_json(args.file, "a calibration file (cam.json, he.json or np.json)", CommandError)
    who = args.who or f"cli:{getpass.getuser()}"

    def go(cfg: CellConfig, store: Any) -> dict[str, Any]:
        try:
            return add_calibration(store, cfg, data, who, args.kind, args.camera, args.robot, args.note,
                                   source=str(args.file))
        except CalibrationFileError as exc:
            raise CommandError(str(exc)) from None

    return _with_store(args, go, must_exist=False)
