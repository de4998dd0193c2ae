"""A damaged store is told apart from a bug, and cellctl says how to restore it (SQLite files)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from cellctl.cli import main
from cellctl.config import load_config
from cellctl.store import CorruptRecord, Store, StoreDamaged, StoreError, StoreUnavailable, open_store
from cellctl.store.integrity import quick_check
from tests.store.helpers import damage_table, populate, snapshot
from tests.store.pgcluster import PostgresCluster

RESTORE = "cellctl store restore --config"


def populated(db: Path) -> dict[str, int]:
    with Store(f"sqlite:///{db}", "c") as s:
        return populate(s)


def test_a_damaged_table_raises_store_damaged_with_the_restore_command(tmp_path: Path) -> None:
    db = tmp_path / "store.db"
    ids = populated(db)
    damage_table(db, "calibrations")
    assert quick_check(db) is not None
    with Store(f"sqlite:///{db}", "c") as s:
        assert s.problem is None
        with pytest.raises(StoreDamaged, match=f"store .*store.db is damaged \\(database disk image is malformed\\); "
                                               f"stop cellctl, then restore the last backup .*{RESTORE}"):
            s.list_calibrations()
        with pytest.raises(StoreDamaged):
            s.active("handeye", "cam0", "ur0")
        # Other tables still answer, and the store keeps saying it is damaged.
        assert [r.recipe_id for r in s.list_recipes()] == [2, 7]
        assert s.problem is not None and "is damaged" in s.problem
        with pytest.raises(StoreDamaged):
            s.get_calibration(ids["cam1"])


def test_stored_text_that_is_not_json_is_damage_not_a_bug(tmp_path: Path) -> None:
    db = tmp_path / "store.db"
    populated(db)
    conn = sqlite3.connect(db)
    conn.execute("UPDATE recipes SET data_json = '{\"model\": \"bolt.js' WHERE recipe_id = 2")
    conn.commit()
    conn.close()
    with Store(f"sqlite:///{db}", "c") as s:
        with pytest.raises(StoreDamaged, match="recipe 2 is not JSON"):
            s.get_recipe(2)
        assert s.problem is not None
        assert s.get_recipe(7).version == 2


def test_a_checksum_mismatch_is_damage(tmp_path: Path) -> None:
    db = tmp_path / "store.db"
    ids = populated(db)
    conn = sqlite3.connect(db)
    conn.execute("DROP TRIGGER calibrations_immutable")
    conn.execute("UPDATE calibrations SET result_json = '{\"rms_px\":0.01}' WHERE id = ?", (ids["cam2"],))
    conn.commit()
    conn.close()
    with Store(f"sqlite:///{db}", "c") as s:
        with pytest.raises(CorruptRecord, match=f"does not match its checksum.*is damaged.*{RESTORE}") as err:
            s.get_calibration(ids["cam2"])
        assert isinstance(err.value, StoreDamaged)
        assert s.problem is not None


def test_a_bug_stays_a_plain_store_error(tmp_path: Path) -> None:
    """SQL the database refuses for a reason of ours is not dressed as an outage."""
    with Store(f"sqlite:///{tmp_path / 'store.db'}", "c") as s:
        with pytest.raises(StoreError) as err, s._read() as conn:
            conn.exec_driver_sql("SELECT no_such_column FROM calibrations")
        assert type(err.value) is StoreError and s.problem is None


def _config(tmp: Path) -> Path:
    cfg = tmp / "cell.yaml"
    cfg.write_text(f"cell_id: line1\nstore:\n  path: {tmp / 'data' / 'line1.db'}\n  backup_dir: {tmp / 'bk'}\n")
    return cfg


@pytest.mark.parametrize("damaged", ["calibrations", "robot_latches"])
def test_cli_backs_up_lists_and_restores_a_damaged_store(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         damaged: str) -> None:
    cfg = _config(tmp_path)
    db = tmp_path / "data" / "line1.db"
    with open_store(load_config(cfg)) as s:
        populate(s)
        before = snapshot(s)
        s.set_latch("ur0", "operator", "Stop", 1_796_000_000.0)  # live state, not in the backup
    assert main(["store", "backup", "--config", str(cfg)]) == 0
    assert main(["store", "backup", "--config", str(cfg), "--format", "json"]) == 0
    capsys.readouterr()
    assert main(["store", "backups", "--config", str(cfg)]) == 0

    listed = json.loads(capsys.readouterr().out)
    assert listed["dir"] == str(tmp_path / "bk") and len(listed["backups"]) == 2
    newest = listed["backups"][0]["file"]
    assert newest.endswith(".json") and Path(newest).name.startswith("line1-")

    damage_table(db, damaged)
    assert main(["store", "info", "--config", str(cfg)]) == 2
    assert "is damaged (database disk image is malformed); stop cellctl" in capsys.readouterr().err
    assert main(["store", "restore", "--config", str(cfg), "--latest"]) == 2
    assert "with --force it is renamed line1.db.damaged-" in capsys.readouterr().err
    assert main(["store", "restore", "--config", str(cfg), "--latest", "--force"]) == 0
    printed = capsys.readouterr()
    out = json.loads(printed.out)
    assert out["from"] == newest and Path(out["damaged_store_set_aside"]).name.startswith("line1.db.damaged-")
    assert Path(out["damaged_store_set_aside"]).exists() and quick_check(db) is None
    with open_store(load_config(cfg)) as s:
        after = snapshot(s)
        latches = s.latches()
    assert after["records"] == before["records"] and after["recipes"] == before["recipes"]
    if damaged == "calibrations":  # the latch table could be read: the robot stays latched
        assert out["latches_carried_over"] == ["ur0"]
        assert [(x.robot_id, x.latched_by, x.reason) for x in latches] == [("ur0", "operator", "Stop")]
        assert [e.action for e in after["audit"][:2]] == ["robot.latch", "store.restore"]
    else:  # it could not: said so, loudly
        assert out["latches_carried_over"] is None and latches == []
        assert "Stop latches stored in" in printed.err and "check every robot" in printed.err
        assert after["audit"][0].action == "store.restore"


def test_restore_latest_without_backups_says_where_it_looked(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _config(tmp_path)
    assert main(["store", "restore", "--config", str(cfg), "--latest"]) == 2
    err = capsys.readouterr().err
    assert f"no backups of cell 'line1' in {tmp_path / 'bk'}; give the backup file with --from FILE" in err


def test_an_unreachable_database_is_unavailable_until_it_is_back(postgres: PostgresCluster,
                                                                 postgres_url: str, cell_id: str) -> None:
    with Store(postgres_url, cell_id) as s:
        populate(s)
        postgres.pause()
        try:
            with pytest.raises(StoreUnavailable, match="is unreachable .*check that the database server runs") as err:
                s.list_recipes()
            assert not isinstance(err.value, StoreDamaged)
            assert s.problem is not None and "is unreachable" in s.problem
        finally:
            postgres.resume()
        assert [r.recipe_id for r in s.list_recipes()] == [2, 7]
        assert s.problem is None  # an outage that passed is no longer reported


def test_a_file_that_cannot_be_opened_is_not_called_damaged(tmp_path: Path) -> None:
    """Restoring a backup would not help a store that cannot be opened: it is unavailable, not damaged."""
    (tmp_path / "store.db").mkdir()  # what SQLite meets where a file should be: cannot open
    with pytest.raises(StoreUnavailable, match=r"store.db cannot be read to check it \(") as err:
        quick_check(tmp_path / "store.db")
    assert not isinstance(err.value, StoreDamaged)
    (tmp_path / "junk.db").write_bytes(b"not a database" * 400)
    assert quick_check(tmp_path / "junk.db") == "file is not a database"
