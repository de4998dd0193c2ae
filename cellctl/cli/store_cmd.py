"""``cellctl store backup|restore|info``: back up and restore the cell's calibration/recipe/audit store.

A SQLite store is backed up with SQLite's online backup API (the service may keep running); a
PostgreSQL store as a JSON dump of this cell's rows. Restore reads either, refuses to overwrite a
non-empty store unless ``--force``, and replaces the cell's rows in one transaction.
"""

from __future__ import annotations

import argparse
import getpass
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "store", help="back up / restore the calibration, recipe and audit store",
        description="Back up and restore the cell's store (calibrations, activations, recipes, audit log).")
    ssub = p.add_subparsers(dest="store_command", metavar="ACTION", required=True)

    b = ssub.add_parser("backup", help="write a backup of this cell's store to a file",
                        description="SQLite: an online copy of the database file (sqlite format); "
                                    "PostgreSQL: a JSON dump of this cell's rows (json format).")
    b.add_argument("--config", required=True, help="cell.yaml naming the store (store.url / store.path)")
    b.add_argument("--out", required=True, help="the backup file to write (replaced atomically)")
    b.add_argument("--format", choices=("sqlite", "json"), default=None,
                   help="sqlite (default for a SQLite store) or json (default for PostgreSQL; works for both)")
    b.set_defaults(func=run_backup)

    r = ssub.add_parser("restore", help="restore this cell's store from a backup file",
                        description="Reads a sqlite or json backup, refuses a non-empty store unless --force, "
                                    "and replaces the cell's rows in one transaction (all or nothing).")
    r.add_argument("--config", required=True, help="cell.yaml naming the store (store.url / store.path)")
    r.add_argument("--from", dest="src", required=True, help="the backup file (from cellctl store backup)")
    r.add_argument("--force", action="store_true", help="replace a store that already holds rows of this cell")
    r.add_argument("--who", default=None, help="name logged in the audit entry (default: cli:<user>)")
    r.set_defaults(func=run_restore)

    i = ssub.add_parser("info", help="where the store is and how many rows this cell has in it")
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


def _with_store(args: argparse.Namespace, fn: Callable[[Any], dict[str, Any]], must_exist: bool) -> dict[str, Any]:
    from cellctl.config import load_config
    from cellctl.store import Store, store_url
    from cellctl.store.backends import backend_of

    cfg = load_config(args.config)
    with _store_errors():
        url = store_url(cfg)
        if must_exist and backend_of(url) == "sqlite" and not Path(str(url.database)).exists():
            raise CommandError(f"no store at {url.database} for cell {cfg.cell_id!r}; nothing to back up "
                               "(check store.path in the config)")
        with Store(url, cfg.cell_id) as store:
            return fn(store)


def run_backup(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.store.backup import backup

    return _with_store(args, lambda store: backup(store, args.out, args.format), must_exist=True)


def run_restore(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl.store.backup import restore

    if not Path(args.src).is_file():
        raise CommandError(f"--from {args.src}: no such file; give a file written by cellctl store backup")
    who = args.who or f"cli:{getpass.getuser()}"
    return _with_store(args, lambda store: restore(store, args.src, who, force=args.force), must_exist=False)


def run_info(args: argparse.Namespace) -> dict[str, Any]:
    return _with_store(args, lambda store: {"backend": store.backend, "store": store.describe(),
                                            "cell_id": store.cell_id, "counts": store.counts()}, must_exist=False)
