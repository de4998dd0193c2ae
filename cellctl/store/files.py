"""Files and folders that hold the store, made readable by the service's user only.

Mode 0600 for files and 0700 for folders we create, set explicitly so the process umask (0022 on
most desktops) does not matter. SQLite gives a database's ``-wal``, ``-shm`` and ``-journal``
files the mode of the database file, so creating the database file 0600 before SQLite opens it
covers them too. Folders that already exist keep their mode (systemd's ``StateDirectory`` sets its
own, 0750).

Run as root (``sudo cellctl store restore ...``) in a folder that belongs to another user (the
service's), a new file or folder is given to that folder's owner, as SQLite does with the
``-wal``/``-shm`` files of a database: a restored store must stay readable by the service.
"""

from __future__ import annotations

import os
from pathlib import Path

FILE_MODE = 0o600
DIR_MODE = 0o700
SIDE_FILES = ("-wal", "-shm", "-journal")
"""SQLite's files beside a database ``x.db``: ``x.db-wal``, ``x.db-shm``, ``x.db-journal``."""


def private_dir(path: Path) -> None:
    """Create ``path`` and its missing parents with mode 0700; existing folders are left as they are."""
    missing: list[Path] = []
    p = path
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    for d in reversed(missing):
        try:
            os.mkdir(d, DIR_MODE)
        except FileExistsError:
            continue
        os.chmod(d, DIR_MODE)
        _give_to_folder_owner(d)


def create_private(path: Path) -> bool:
    """Create ``path`` as an empty file with mode 0600; False (nothing done) when it exists already."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, FILE_MODE)
    except FileExistsError:
        return False
    try:
        os.fchmod(fd, FILE_MODE)
        _give_to_folder_owner(path, fd)
    finally:
        os.close(fd)
    return True


def open_private(path: Path) -> int:
    """A new file ``path`` (it must not exist) with mode 0600, open for writing: a descriptor for ``os.fdopen``."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, FILE_MODE)
    os.fchmod(fd, FILE_MODE)
    _give_to_folder_owner(path, fd)
    return fd


def _give_to_folder_owner(path: Path, fd: int | None = None) -> None:
    if os.geteuid() != 0:
        return
    st = os.stat(path.parent)
    if st.st_uid != 0:
        if fd is None:
            os.chown(path, st.st_uid, st.st_gid, follow_symlinks=False)
        else:
            os.fchown(fd, st.st_uid, st.st_gid)


def tighten(db: Path) -> list[str]:
    """Drop group and other permissions of the database ``db`` and its side files that this user owns.

    For stores created by an older cellctl (0644); returns the files changed.
    """
    changed = []
    for p in (db, *(db.with_name(db.name + s) for s in SIDE_FILES)):
        try:
            st = os.stat(p, follow_symlinks=False)
        except FileNotFoundError:
            continue
        if st.st_uid == os.geteuid() and st.st_mode & 0o077:
            try:
                os.chmod(p, st.st_mode & 0o700)
            except OSError:  # a read-only mount: the store can still be read
                continue
            changed.append(str(p))
    return changed
