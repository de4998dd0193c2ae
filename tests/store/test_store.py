"""The store's contract, run unchanged against SQLite and a real PostgreSQL server."""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

import cellctl
from cellctl.config import parse_config
from cellctl.store import (
    CorruptRecord,
    InvalidInput,
    NotFound,
    NothingToRollBack,
    RestoreRefused,
    Store,
    StoreDamaged,
    StoreFormatError,
    open_store,
    store_url,
)
from cellctl.store.backup import backup, dump_cell, restore
from tests.store.helpers import populate, snapshot, without_ids
from tests.store.pgcluster import PostgresCluster


def test_versions_are_immutable_and_numbered_per_key(store: Store) -> None:
    t0 = time.time()
    inputs = {"observations": [{"image": f"{i}.png", "points": [[i, 2.0 * i]]} for i in range(5)],
              "robot_poses": [[0.1, 0.2, 0.3, 0.0, 3.1, 0.0]]}
    v1 = store.save_calibration("camera", "cam0", None, {"rms_px": 0.2}, inputs, "alice", note="first")
    v2 = store.save_calibration("camera", "cam0", None, {"rms_px": 0.1}, {"views": 3}, "bob")
    other = store.save_calibration("camera", "cam1", None, {"rms_px": 0.3}, {}, "bob")
    he = store.save_calibration("handeye", "cam0", "ur0", {"setup": "eye-in-hand"}, {}, "bob")
    he2 = store.save_calibration("handeye", "cam0", "ur1", {"setup": "eye-in-hand"}, {}, "bob")
    assert (v1.version, v2.version, other.version, he.version, he2.version) == (1, 2, 1, 1, 1)
    assert len({v1.id, v2.id, other.id, he.id, he2.id}) == 5
    got = store.get_calibration(v1.id)
    assert got.inputs == inputs and got.result == {"rms_px": 0.2}
    assert (got.creator, got.note, got.tool_version, got.kind, got.robot_id) == (
        "alice", "first", cellctl.__version__, "camera", None)
    assert t0 <= got.created_s <= time.time()
    assert got.sha256 == v1.sha256 and not got.active
    assert store.get_calibration(he.id).robot_id == "ur0"
    # saving again never touched version 1
    assert store.get_calibration(v1.id) == got
    with pytest.raises(sa.exc.DBAPIError, match="immutable"), store.engine.begin() as conn:
        conn.execute(sa.text("UPDATE calibrations SET note = 'tampered'"))
    assert store.get_calibration(v1.id).note == "first"


def test_payloads_accept_numpy_and_refuse_the_unstorable(store: Store) -> None:
    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    rec = store.save_calibration("camera", "cam0", None, {"K": K, "rms_px": np.float64(0.1)}, {}, "a")
    assert store.get_calibration(rec.id).result == {"K": K.tolist(), "rms_px": 0.1}
    with pytest.raises(InvalidInput, match="calibration inputs cannot be stored as JSON.*object"):
        store.save_calibration("camera", "cam0", None, {}, {"x": object()}, "a")
    with pytest.raises(InvalidInput, match="kind 'lens'"):
        store.save_calibration("lens", "cam0", None, {}, {}, "a")  # type: ignore[arg-type]
    with pytest.raises(InvalidInput, match="pass robot_id=None"):
        store.save_calibration("camera", "cam0", "ur0", {}, {}, "a")
    with pytest.raises(InvalidInput, match="pass its robot_id"):
        store.save_calibration("npoint", "cam0", None, {}, {}, "a")
    with pytest.raises(InvalidInput, match="creator must be a non-empty string"):
        store.save_calibration("camera", "cam0", None, {}, {}, "")
    assert [s.version for s in store.list_calibrations()] == [1]  # refused saves stored nothing


def test_not_found_is_a_key_error_with_a_clear_message(store: Store, store_url: str) -> None:
    with pytest.raises(KeyError) as info:
        store.get_calibration(424242)
    assert isinstance(info.value, NotFound)
    assert str(info.value).startswith(f"calibration 424242 not found in the store of cell {store.cell_id!r}")
    with pytest.raises(NotFound, match="recipe 5 not found"):
        store.get_recipe(5)
    with pytest.raises(NotFound):
        store.activate(424242, "eng")
    # another cell in the same database is invisible
    rec = store.save_calibration("camera", "cam0", None, {}, {}, "a")
    with Store(store_url, store.cell_id + "-other") as other:
        with pytest.raises(NotFound):
            other.get_calibration(rec.id)
        assert other.list_calibrations() == [] and other.audit_log() == [] and other.is_empty()
        other.save_calibration("camera", "cam0", None, {}, {}, "a")
        assert other.list_calibrations()[0].version == 1
    assert [s.id for s in store.list_calibrations()] == [rec.id]


def test_list_filters_and_active_flags(store: Store) -> None:
    a = store.save_calibration("camera", "cam0", None, {}, {}, "a")
    b = store.save_calibration("camera", "cam1", None, {}, {}, "a")
    c = store.save_calibration("handeye", "cam0", "ur0", {}, {}, "a")
    d = store.save_calibration("npoint", "cam1", "ur0", {}, {}, "a")
    store.activate(c.id, "eng")
    assert [s.id for s in store.list_calibrations()] == [a.id, b.id, c.id, d.id]
    assert [s.id for s in store.list_calibrations(kind="camera")] == [a.id, b.id]
    assert [s.id for s in store.list_calibrations(camera_id="cam1")] == [b.id, d.id]
    assert [s.id for s in store.list_calibrations(robot_id="ur0")] == [c.id, d.id]
    assert [s.id for s in store.list_calibrations(kind="handeye", camera_id="cam0", robot_id="ur0")] == [c.id]
    assert [s.active for s in store.list_calibrations()] == [False, False, True, False]
    assert store.get_calibration(c.id).summary() == store.list_calibrations(kind="handeye")[0]


def test_activate_one_per_key_and_rollback_walks_back(store: Store) -> None:
    v = [store.save_calibration("handeye", "cam0", "ur0", {"i": i}, {}, "a") for i in range(3)]
    cam = store.save_calibration("camera", "cam0", None, {}, {}, "a")
    assert store.active("handeye", "cam0", "ur0") is None
    with pytest.raises(NothingToRollBack, match="handeye/cam0/ur0"):
        store.rollback("handeye", "cam0", "ur0", "eng")
    store.activate(cam.id, "eng")
    for rec in v:
        assert store.activate(rec.id, "eng").active
        active = store.active("handeye", "cam0", "ur0")
        assert active is not None and active.id == rec.id
    assert [s.active for s in store.list_calibrations(kind="handeye")] == [False, False, True]
    back = store.rollback("handeye", "cam0", "ur0", "eng")
    assert back is not None and back.id == v[1].id and back.active
    back = store.rollback("handeye", "cam0", "ur0", "eng")
    assert back is not None and back.id == v[0].id
    assert store.rollback("handeye", "cam0", "ur0", "eng") is None  # before the first activation: none
    assert store.active("handeye", "cam0", "ur0") is None
    with pytest.raises(NothingToRollBack):
        store.rollback("handeye", "cam0", "ur0", "eng")
    # activating from "none" and rolling back returns to "none"
    store.activate(v[2].id, "eng")
    assert store.rollback("handeye", "cam0", "ur0", "eng") is None
    cam_active = store.active("camera", "cam0")
    assert cam_active is not None and cam_active.id == cam.id  # the other key never moved
    history = store.activation_history("handeye", "cam0", "ur0")
    assert [(h["action"], h["calibration_id"]) for h in history] == [
        ("activate", v[0].id), ("activate", v[1].id), ("activate", v[2].id), ("rollback", v[1].id),
        ("rollback", v[0].id), ("rollback", None), ("activate", v[2].id), ("rollback", None)]


def test_acts_are_logged(store: Store) -> None:
    a = store.save_calibration("camera", "cam0", None, {}, {}, "alice", note="n")
    b = store.save_calibration("camera", "cam0", None, {}, {}, "alice")
    store.activate(a.id, "eng1")
    store.activate(a.id, "eng1")  # already active: no new state, still logged
    store.activate(b.id, "eng2")
    store.rollback("camera", "cam0", None, "eng3")
    store.audit("op", "robot.move", "ur0", {"x_mm": 1.5, "speed_m_s": 0.1}, "refused: outside envelope")
    log = store.audit_log()
    assert [(e.who, e.action, e.result) for e in log] == [
        ("op", "robot.move", "refused: outside envelope"),
        ("eng3", "calibration.rollback", f"ok: active {a.id}"),
        ("eng2", "calibration.activate", "ok: active camera/cam0"),
        ("eng1", "calibration.activate", "already active"),
        ("eng1", "calibration.activate", "ok: active camera/cam0"),
        ("alice", "calibration.save", "ok"),
        ("alice", "calibration.save", "ok"),
    ]
    assert log[0].detail == {"x_mm": 1.5, "speed_m_s": 0.1} and log[0].target == "ur0"
    assert log[1].detail["from_calibration_id"] == b.id and log[1].detail["to_calibration_id"] == a.id
    assert log[-1].target == f"calibration:{a.id}" and log[-1].detail["version"] == 1
    assert all(x.at_s >= y.at_s for x, y in zip(log, log[1:], strict=False))
    assert len(store.activation_history("camera", "cam0")) == 3
    assert [e.who for e in store.audit_log(limit=2)] == ["op", "eng3"]
    assert [e.who for e in store.audit_log(action="calibration.activate")] == ["eng2", "eng1", "eng1"]
    with pytest.raises(InvalidInput, match="limit must be an integer in 1..10000"):
        store.audit_log(limit=0)


def test_recipes_are_versioned_latest_wins(store: Store) -> None:
    r1 = store.save_recipe(3, "bolt", {"min_score": 0.8}, "alice")
    r2 = store.save_recipe(3, "bolt", {"min_score": 0.9}, "bob")
    store.save_recipe(1, "nut", {"min_score": 0.7}, "alice")
    assert (r1.version, r2.version) == (1, 2)
    latest = store.get_recipe(3)
    assert (latest.version, latest.data, latest.creator) == (2, {"min_score": 0.9}, "bob")
    assert store.get_recipe(3, version=1).data == {"min_score": 0.8}
    assert [(r.recipe_id, r.version, r.name) for r in store.list_recipes()] == [(1, 1, "nut"), (3, 2, "bolt")]
    with pytest.raises(NotFound, match="recipe 3 version 9"):
        store.get_recipe(3, version=9)
    with pytest.raises(InvalidInput, match="non-negative integer"):
        store.save_recipe(-1, "x", {}, "a")
    assert [e.target for e in store.audit_log(action="recipe.save")] == ["recipe:1", "recipe:3", "recipe:3"]


def test_threads_share_one_store(store: Store) -> None:
    n_threads, per_thread = 6, 8
    errors: list[BaseException] = []
    ids: list[int] = []
    lock = threading.Lock()

    def work(k: int) -> None:
        try:
            for i in range(per_thread):
                rec = store.save_calibration("handeye", "cam0", "ur0", {"k": k, "i": i}, {"pad": "x" * 2000}, f"t{k}")
                store.activate(rec.id, f"t{k}")
                store.audit(f"t{k}", "robot.move", "ur0", {"i": i}, "ok")
                store.list_calibrations()
                with lock:
                    ids.append(rec.id)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors, errors
    n = n_threads * per_thread
    summaries = store.list_calibrations()
    assert sorted(s.version for s in summaries) == list(range(1, n + 1))
    assert sorted(s.id for s in summaries) == sorted(ids)
    assert sum(s.active for s in summaries) == 1
    assert len(store.activation_history("handeye", "cam0", "ur0")) == n
    assert len(store.audit_log(limit=10_000, action="robot.move")) == n
    assert len(store.audit_log(limit=10_000)) == 3 * n


def test_reopening_keeps_everything(store_url: str, cell_id: str) -> None:
    with Store(store_url, cell_id) as s:
        populate(s)
        before = snapshot(s)
    with Store(store_url, cell_id) as s:
        assert snapshot(s) == before


def test_newer_schema_is_refused(store_url: str, cell_id: str, request: pytest.FixtureRequest) -> None:
    if store_url.startswith("postgresql"):  # its own database: the shared one must stay usable
        cluster: PostgresCluster = request.getfixturevalue("postgres")
        store_url = cluster.create_database(f"schema_{cell_id}".replace("-", "_"))
    with Store(store_url, cell_id) as s, s.engine.begin() as conn:
        conn.execute(sa.text("UPDATE cellctl_meta SET value = '99' WHERE key = 'schema_version'"))
    with pytest.raises(StoreFormatError, match="schema version 99, newer than this cellctl supports"):
        Store(store_url, cell_id)


def test_a_tampered_payload_is_detected(store: Store) -> None:
    rec = store.save_calibration("camera", "cam0", None, {"rms_px": 0.1}, {"views": [1, 2]}, "a")
    with store.engine.begin() as conn:  # damage outside cellctl: bypass the immutability trigger
        if store.backend == "sqlite":
            conn.execute(sa.text("DROP TRIGGER calibrations_immutable"))
        else:
            conn.execute(sa.text("ALTER TABLE calibrations DISABLE TRIGGER calibrations_immutable"))
        conn.execute(sa.text("UPDATE calibrations SET result_json = :r WHERE id = :i"),
                     {"r": '{"rms_px":0.01}', "i": rec.id})
        if store.backend == "postgresql":
            conn.execute(sa.text("ALTER TABLE calibrations ENABLE TRIGGER calibrations_immutable"))
    with pytest.raises(CorruptRecord, match=f"calibration {rec.id}: stored payload does not match its checksum"):
        store.get_calibration(rec.id)


def test_restore_is_all_or_nothing(store: Store, tmp_path: Path) -> None:
    populate(store)
    before = snapshot(store)
    dump_file = tmp_path / "dump.json"
    backup(store, dump_file, "json")
    # a backup whose last table has a row the schema refuses (NULL who): nothing may change
    dump = json.loads(dump_file.read_text())
    audit = dump["tables"]["audit"]
    audit["rows"][-1][audit["columns"].index("who")] = None
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(dump))
    with pytest.raises(RestoreRefused, match="nothing was changed"):
        restore(store, bad, "test", force=True)
    assert snapshot(store) == before
    # the good one replaces the rows (with --force) and logs the act
    result = restore(store, dump_file, "test", force=True)
    assert result["replaced"] and result["counts"]["calibrations"] == 3
    after = snapshot(store)
    assert after["audit"][0].action == "store.restore" and after["audit"][0].who == "test"
    assert {**after, "audit": after["audit"][1:]} == before
    # new writes continue after the restored ids
    rec = store.save_calibration("camera", "cam0", None, {}, {}, "a")
    assert rec.id > max(s.id for s in before["summaries"]) and rec.version == 3


def test_sqlite_backup_restores_into_postgresql(tmp_path: Path, postgres_url: str, cell_id: str) -> None:
    """A cell moves from its embedded SQLite file into the plant's PostgreSQL database, where other
    cells already use the ids 1, 2, ...: its rows are renumbered and every reference follows."""
    with Store(postgres_url, cell_id + "-neighbour") as neighbour:
        populate(neighbour)
    with Store(f"sqlite:///{tmp_path / 'cell.db'}", cell_id) as lite:
        ids = populate(lite)
        before = snapshot(lite)
        backup(lite, tmp_path / "cell.backup.db")
        assert len(dump_cell(lite)["tables"]["calibrations"]["rows"]) == 3
    with Store(postgres_url, cell_id) as pg:
        result = restore(pg, tmp_path / "cell.backup.db", "migration")
        after = snapshot(pg)
        entry = pg.audit_log(1)[0]
        assert result["ids_renumbered"] and entry.action == "store.restore"
        renumbered = entry.detail["calibration_ids_renumbered"]
        assert set(renumbered) == {str(i) for i in ids.values()}
        active = pg.active("handeye", "cam0", "ur0")
        assert active is not None and active.id == renumbered[str(ids["he"])]
    assert without_ids({**after, "audit": after["audit"][1:]}) == without_ids(before)


def test_open_store_follows_the_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, postgres_url: str) -> None:
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))
    cfg = parse_config({"cell_id": "line3"})
    assert store_url(cfg).database == str(tmp_path / "data" / "line3.db")
    with open_store(cfg) as s:
        assert s.backend == "sqlite" and s.cell_id == "line3"
        assert (tmp_path / "data" / "line3.db").exists()
        with s.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    with open_store(parse_config({"cell_id": "line3", "store": {"path": str(tmp_path / "x.db")}})) as s:
        assert s.url.database == str(tmp_path / "x.db")
    pg_cfg = parse_config({"cell_id": "line3", "store": {"url": postgres_url.replace("+psycopg", "")}})
    with open_store(pg_cfg) as s:
        assert s.backend == "postgresql" and s.url.drivername == "postgresql+psycopg"
    with pytest.raises(InvalidInput, match="store.url and store.path both given"):
        store_url(parse_config({"store": {"url": postgres_url, "path": "x.db"}}))
    with pytest.raises(InvalidInput, match="backend 'mysql' is not supported"):
        Store("mysql://u@127.0.0.1/x", "c")
    with pytest.raises(InvalidInput, match="in-memory SQLite"):
        Store("sqlite://", "c")
    (tmp_path / "junk.db").write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreDamaged, match=r"junk.db is damaged \(file is not a database\).*cellctl store restore"):
        Store(f"sqlite:///{tmp_path / 'junk.db'}", "c")


def test_postgresql_without_its_driver_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    """psycopg is an extra (``cellctl[postgres]``): a PostgreSQL URL without it is a config error saying so."""
    monkeypatch.setitem(sys.modules, "psycopg", None)  # how Python marks a module as not importable
    with pytest.raises(InvalidInput, match=r"needs its driver.*pip install 'cellctl\[postgres\]'"):
        Store("postgresql+psycopg://u@127.0.0.1:1/x", "c")


def test_backup_is_online_and_consistent(store: Store, tmp_path: Path) -> None:
    """A backup taken while another thread keeps writing is one consistent moment of the store."""
    stop = threading.Event()
    written: list[int] = []

    def writer() -> None:
        while not stop.is_set():
            written.append(store.save_calibration("camera", "cam0", None, {"i": len(written)},
                                                  {"pad": "y" * 20_000}, "w").id)

    t = threading.Thread(target=writer)
    t.start()
    try:
        while len(written) < 3:
            time.sleep(0.01)
        backups = [backup(store, tmp_path / f"b{i}", None) for i in range(3)]
    finally:
        stop.set()
        t.join(timeout=60)
    for i, b in enumerate(backups):
        assert b["format"] == ("sqlite" if store.backend == "sqlite" else "json")
        # each version's row and its audit entry are in the same backup, or neither is
        assert b["counts"]["calibrations"] == b["counts"]["audit"] >= 3
        with Store(f"sqlite:///{tmp_path / f'r{i}.db'}", store.cell_id) as target:
            restore(target, tmp_path / f"b{i}", "test")
            got = target.list_calibrations()
            assert [s.version for s in got] == list(range(1, len(got) + 1))
            assert all(target.get_calibration(s.id).inputs == {"pad": "y" * 20_000} for s in got)
    assert len(written) >= backups[-1]["counts"]["calibrations"]
