"""``cellctl store backup|restore``: backup → wipe → restore round trips on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from cellctl.cli import main
from cellctl.config import load_config
from cellctl.store import open_store
from tests.store.helpers import populate, snapshot, without_ids
from tests.store.pgcluster import PostgresCluster

CELLCTL = str(Path(sys.executable).with_name("cellctl"))


@pytest.fixture(scope="module")
def postgres() -> Iterator[PostgresCluster]:
    cluster = PostgresCluster()
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


def _cellctl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CELLCTL, *args], capture_output=True, text=True, timeout=120)


def _config(path: Path, cell_id: str, store: dict[str, str]) -> Path:
    lines = [f"cell_id: {cell_id}", "store:"] + [f"  {k}: {v}" for k, v in store.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def _sqlite_case(tmp_path: Path) -> tuple[Path, Callable[[], None]]:
    db = tmp_path / "data" / "line1.db"
    cfg = _config(tmp_path / "cell.yaml", "line1", {"path": str(db)})

    def wipe() -> None:
        for p in db.parent.glob(db.name + "*"):
            p.unlink()

    return cfg, wipe


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_backup_wipe_restore_round_trip(backend: str, tmp_path: Path, request: pytest.FixtureRequest,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    if backend == "sqlite":
        cfg, wipe = _sqlite_case(tmp_path)
    else:
        cluster: PostgresCluster = request.getfixturevalue("postgres")
        cluster.create_database("plant")
        cfg = _config(tmp_path / "cell.yaml", "line1", {"url": cluster.url("plant")})
        with open_store(load_config(_config(tmp_path / "other.yaml", "line2", {"url": cluster.url("plant")}))) as s:
            populate(s)  # another cell in the same database: not part of line1's backup

        def wipe_database() -> None:
            cluster.drop_database("plant")
            cluster.create_database("plant")

        wipe = wipe_database

    config = load_config(cfg)
    with open_store(config) as store:
        populate(store)
        before = snapshot(store)
    out = tmp_path / "backup.bin"

    r = _cellctl("store", "backup", "--config", str(cfg), "--out", str(out))
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert result["format"] == ("sqlite" if backend == "sqlite" else "json")
    assert result["counts"] == {"calibrations": 3, "activations": 4, "recipes": 3, "audit": 11}
    assert result["bytes"] == out.stat().st_size > 0
    if backend == "postgresql":
        assert json.loads(out.read_text())["cell_id"] == "line1"  # only this cell's rows

    wipe()
    with open_store(config) as store:
        assert store.is_empty()

    r = _cellctl("store", "restore", "--config", str(cfg), "--from", str(out), "--who", "maint")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["replaced"] is False
    with open_store(config) as store:
        after = snapshot(store)
    restore_entry = after["audit"][0]
    assert (restore_entry.action, restore_entry.who) == ("store.restore", "maint")
    assert {**after, "audit": after["audit"][1:]} == before

    # a second restore would overwrite a non-empty store: refused with one line, store unchanged
    # (in-process from here on: the console script was exercised above)
    capsys.readouterr()
    assert main(["store", "restore", "--config", str(cfg), "--from", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "cellctl: error: restore: the store of cell 'line1' is not empty (3 calibrations, 4 activations, "
        "3 recipes, 12 audit); pass --force to replace it with the backup"]
    with open_store(config) as store:
        assert snapshot(store) == after
        store.save_calibration("camera", "cam0", None, {"after": True}, {}, "alice")

    assert main(["store", "restore", "--config", str(cfg), "--from", str(out), "--force"]) == 0
    assert json.loads(capsys.readouterr().out)["replaced"] is True
    with open_store(config) as store:
        final = snapshot(store)
    assert {**final, "audit": final["audit"][1:]} == before  # the extra version is gone


def test_sqlite_cell_moves_to_postgresql(tmp_path: Path, postgres: PostgresCluster,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    lite_cfg, _ = _sqlite_case(tmp_path)
    with open_store(load_config(lite_cfg)) as lite:
        populate(lite)
        before = snapshot(lite)
    postgres.create_database("moved")
    pg_cfg = _config(tmp_path / "pg.yaml", "line1", {"url": postgres.url("moved")})
    for fmt in ("sqlite", "json"):
        out = tmp_path / f"b.{fmt}"
        assert main(["store", "backup", "--config", str(lite_cfg), "--out", str(out), "--format", fmt]) == 0
        assert main(["store", "restore", "--config", str(pg_cfg), "--from", str(out), "--force"]) == 0
        with open_store(load_config(pg_cfg)) as pg:
            after = snapshot(pg)
        assert without_ids({**after, "audit": after["audit"][1:]}) == without_ids(before)
    capsys.readouterr()


@pytest.mark.parametrize(("case", "message"), [
    ("garbage", "is neither a SQLite store backup nor a JSON store dump"),
    ("other-cell", "is a backup of cell 'line9', not of 'line1'"),
    ("missing", "no such file; give a file written by cellctl store backup"),
    ("no-store", "no store at"),
    ("bad-config", "store.url and store.path both given"),
])
def test_bad_input_gets_one_clear_line(case: str, message: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    cfg, _ = _sqlite_case(tmp_path)
    src = tmp_path / "src"
    if case in ("garbage", "bad-config"):
        src.write_bytes(b"\x00\x01 not a backup")
    elif case == "other-cell":
        other = _config(tmp_path / "other.yaml", "line9", {"path": str(tmp_path / "line9.db")})
        with open_store(load_config(other)) as s:
            populate(s)
        assert main(["store", "backup", "--config", str(other), "--out", str(src), "--format", "json"]) == 0
    if case == "bad-config":
        cfg = _config(tmp_path / "bad.yaml", "line1", {"path": "x.db", "url": "sqlite:////tmp/x.db"})
    capsys.readouterr()
    if case == "no-store":
        code = main(["store", "backup", "--config", str(cfg), "--out", str(tmp_path / "b.db")])
    else:
        code = main(["store", "restore", "--config", str(cfg), "--from", str(src)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("cellctl: error: ") and message in err[0], err
