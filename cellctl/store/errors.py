"""Typed errors of the store; every message says what was wrong and what to do."""

from __future__ import annotations

from cellctl.errors import CellctlError


class StoreError(CellctlError, RuntimeError):
    """Base of the store's errors (a ``RuntimeError``: the CLI prints its message as one line)."""


class NotFound(StoreError, KeyError):
    """A calibration or recipe asked for by id does not exist in this cell's store.

    Also a ``KeyError``, so ``except KeyError`` works, but its ``str()`` is the plain message.
    """

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "not found"


class InvalidInput(StoreError, ValueError):
    """An argument to a store call is malformed (bad kind, empty id, payload not JSON-able)."""


class NothingToRollBack(StoreError, ValueError):
    """``rollback`` was asked for a camera/robot pair that has no earlier activation."""


class StoreFormatError(StoreError):
    """The database was written by a newer cellctl, or is not a cellctl store at all."""


class StoreUnavailable(StoreError):
    """The store cannot be used now: its file is locked, unreadable or on a full disk, or its database
    server is unreachable. The service answers 503 ``store_unavailable`` with the message."""


class StoreDamaged(StoreUnavailable):
    """The store's data is damaged (SQLite says malformed / not a database, a record fails its
    checksum): the message says how to restore the last backup. It stays so until restored."""


class CorruptRecord(StoreDamaged):
    """A stored record's checksum does not match its payload (storage damaged outside cellctl)."""


class RestoreRefused(StoreError):
    """``restore`` would overwrite a non-empty store (without ``force``) or the backup is unusable."""
