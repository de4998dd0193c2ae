"""The calibration/recipe/audit store: SQLite embedded by default, PostgreSQL for many cells.

``open_store(config)`` opens the store a ``cell.yaml`` names: ``store.url`` when given (a
SQLAlchemy URL such as ``postgresql+psycopg://user@127.0.0.1:5432/cellctl``), else the SQLite file
``store.path``, else ``<data dir>/<cell_id>.db`` (see :func:`cellctl.paths.data_dir`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy as sa

from cellctl.store.backends import Backend, parse_url, sqlite_url
from cellctl.store.errors import (
    CorruptRecord,
    InvalidInput,
    NotFound,
    NothingToRollBack,
    RestoreRefused,
    StoreDamaged,
    StoreError,
    StoreFormatError,
    StoreUnavailable,
)
from cellctl.store.records import (
    CALIBRATION_KINDS,
    AuditEntry,
    CalibrationKind,
    CalibrationRecord,
    CalibrationSummary,
    Recipe,
)
from cellctl.store.store import Store

if TYPE_CHECKING:
    from cellctl.config import CellConfig

__all__ = [
    "CALIBRATION_KINDS", "AuditEntry", "Backend", "CalibrationKind", "CalibrationRecord", "CalibrationSummary",
    "CorruptRecord", "InvalidInput", "NotFound", "NothingToRollBack", "Recipe", "RestoreRefused", "Store",
    "StoreDamaged", "StoreError", "StoreFormatError", "StoreUnavailable", "open_store", "store_url",
]


def store_url(config: CellConfig) -> sa.URL:
    """The database URL of the cell's store (see the module docstring for the defaults)."""
    if config.store.url:
        if config.store.path:
            raise InvalidInput("cell.yaml: store.url and store.path both given; keep one "
                               "(path is the SQLite file, url any database)")
        return parse_url(config.store.url)
    if config.store.path:
        return sqlite_url(Path(config.store.path))
    from cellctl.paths import data_dir

    return sqlite_url(data_dir() / f"{config.cell_id}.db")


def open_store(config: CellConfig) -> Store:
    """Open (creating when missing) the store of the cell ``config`` describes."""
    from cellctl.store.integrity import recovery_hint

    return Store(store_url(config), config.cell_id, recovery_hint(config.source))
