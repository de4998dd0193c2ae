"""What ``cellctl serve`` checks about the store before serving, and the modes of the store's files."""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.cli import main
from cellctl.config import CellConfig, load_config
from cellctl.store import Store, StoreDamaged, open_store
from cellctl.store.backup import backup
from cellctl.store.startup import StoreStartRefused, check_store_at_start, marker_path
from tests.store.helpers import damage_table, populate


@pytest.fixture()
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))
    return tmp_path / "data"


@pytest.fixture()
def umask_022() -> Iterator[None]:
    """The umask of most desktops: without explicit modes new files would be 0644."""
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


def config(tmp: Path) -> CellConfig:
    cfg = tmp / "cell.yaml"
    cfg.write_text(f"cell_id: line1\nstore:\n  path: {tmp / 'store' / 'line1.db'}\n  backup_dir: {tmp / 'bk'}\n")
    return load_config(cfg)


def mode(path: Path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_first_start_creates_the_store_silently_and_records_it(tmp_path: Path, data_dir: Path) -> None:
    cfg = config(tmp_path)
    first = check_store_at_start(cfg)
    assert first["first_start"] and (tmp_path / "store" / "line1.db").stat().st_size > 0
    marker = json.loads(marker_path(cfg).read_text())
    assert marker_path(cfg) == data_dir / "line1.store-started.json"
    assert marker["store"].endswith("/store/line1.db") and marker["counts"]["calibrations"] == 0
    again = check_store_at_start(cfg)  # an empty store that was empty before is fine
    assert not again["first_start"]


@pytest.mark.parametrize("what", ["missing", "zero-length", "wiped"])
def test_a_store_gone_after_a_start_refuses_the_start(tmp_path: Path, data_dir: Path, what: str) -> None:
    cfg = config(tmp_path)
    db = tmp_path / "store" / "line1.db"
    with open_store(cfg) as s:
        populate(s)
    audit = check_store_at_start(cfg)["counts"]["audit"]
    size = db.stat().st_size
    for side in ("-wal", "-shm"):
        db.with_name(db.name + side).unlink(missing_ok=True)
    if what == "missing":
        db.unlink()
        found = f"the store {db} does not exist"
    elif what == "zero-length":
        db.write_bytes(b"")
        found = f"the store {db} is empty \\(0 bytes\\)"
    else:  # a valid store without the cell's rows: a fresh file put in its place
        db.unlink()
        Store(f"sqlite:///{db}", "line1").close()
        found = "holds no rows of the cell"
    with pytest.raises(StoreStartRefused) as err:
        check_store_at_start(cfg)
    msg = str(err.value)
    assert msg.startswith("refusing to start: ") and found.replace("\\", "") in msg
    # what the store was at the last start
    assert f"{size} bytes, 3 calibrations, 4 activations, 3 recipe versions, {audit} audit entries;" in msg
    assert f"cellctl store restore --config {cfg.source} --latest --force" in msg
    assert f"cellctl serve --config {cfg.source} --new-store" in msg and f"delete {marker_path(cfg)}" in msg
    # Refusing changed nothing: still refused, and no store was created in the missing one's place.
    with pytest.raises(StoreStartRefused):
        check_store_at_start(cfg)
    assert what != "missing" or not db.exists()
    # Beginning anew is a deliberate act; afterwards the new store is the one recorded.
    assert check_store_at_start(cfg, new_store=True)["counts"]["calibrations"] == 0
    check_store_at_start(cfg)


def test_restoring_the_backup_brings_the_start_back(tmp_path: Path, data_dir: Path) -> None:
    cfg = config(tmp_path)
    db = tmp_path / "store" / "line1.db"
    with open_store(cfg) as s:
        populate(s)
        backup(s, tmp_path / "b.db")
    check_store_at_start(cfg)
    db.write_bytes(b"")
    with pytest.raises(StoreStartRefused):
        check_store_at_start(cfg)
    assert main(["store", "restore", "--config", str(cfg.source), "--from", str(tmp_path / "b.db")]) == 0
    assert check_store_at_start(cfg)["counts"]["calibrations"] == 3


def test_a_damaged_store_refuses_the_start(tmp_path: Path, data_dir: Path) -> None:
    cfg = config(tmp_path)
    db = tmp_path / "store" / "line1.db"
    with open_store(cfg) as s:
        populate(s)
    damage_table(db, "audit")  # a table nothing reads at start: only the integrity check finds it
    restore = f"CELLCTL_DATA_DIR={data_dir} cellctl store restore --config {cfg.source} --latest --force"
    with pytest.raises(StoreDamaged, match=f"refusing to start: the store {db} is damaged .*; restore the last "
                                           f"backup: {restore}"):
        check_store_at_start(cfg)
    assert not marker_path(cfg).exists()


def test_store_files_backups_and_folders_are_private(tmp_path: Path, data_dir: Path, umask_022: None) -> None:
    cfg = config(tmp_path)
    db = tmp_path / "store" / "line1.db"
    check_store_at_start(cfg)
    with open_store(cfg) as s:
        populate(s)  # writes: the WAL and its index exist now
        for f in (db, db.with_name("line1.db-wal"), db.with_name("line1.db-shm")):
            assert mode(f) == 0o600, f
        backup(s, tmp_path / "b.db")
        backup(s, tmp_path / "b.json", "json")
    assert mode(tmp_path / "store") == 0o700 and mode(data_dir) == 0o700
    assert mode(tmp_path / "b.db") == 0o600 and mode(tmp_path / "b.json") == 0o600
    assert mode(marker_path(cfg)) == 0o600
    assert main(["store", "backup", "--config", str(cfg.source)]) == 0
    (made,) = (tmp_path / "bk").iterdir()
    assert mode(tmp_path / "bk") == 0o700 and mode(made) == 0o600


def test_an_older_world_readable_store_is_made_private(tmp_path: Path, umask_022: None) -> None:
    db = tmp_path / "old.db"
    with Store(f"sqlite:///{db}", "c") as s:
        populate(s)
    for f in tmp_path.iterdir():
        os.chmod(f, 0o644)
    with Store(f"sqlite:///{db}", "c") as s:
        s.list_recipes()
    assert {f.name: mode(f) for f in tmp_path.iterdir()} == {f.name: 0o600 for f in tmp_path.iterdir()}


@pytest.mark.skipif(os.geteuid() != 0, reason="what root creates for the service's user: needs root")
def test_root_creates_the_store_for_the_owner_of_its_folder(tmp_path: Path) -> None:
    """``sudo cellctl store restore`` into the service's folder leaves a store the service can open."""
    import pwd

    nobody = pwd.getpwnam("nobody")
    folder = tmp_path / "var-lib-cellctl"
    folder.mkdir()
    os.chown(folder, nobody.pw_uid, nobody.pw_gid)
    db = folder / "store" / "line1.db"
    with Store(f"sqlite:///{db}", "c") as s:
        populate(s)
        backup(s, folder / "b.db")
        made = (db.parent, db, db.with_name("line1.db-wal"), db.with_name("line1.db-shm"), folder / "b.db")
        owners = {p.name: (os.stat(p).st_uid, os.stat(p).st_gid) for p in made}
    assert set(owners.values()) == {(nobody.pw_uid, nobody.pw_gid)}, owners
