"""A damaged store: the routes that touch it answer 503 ``store_unavailable`` saying how to restore it,
``/health`` says so, and ``cellctl serve`` refuses to start on it until the last backup is restored."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.auth import hash_token
from cellctl.cli import main
from cellctl.config import CellConfig, default_config_text, load_config
from cellctl.store import open_store
from tests.store.helpers import damage_table
from tests.support.served import free_port, start_served, stop_served

TOKEN = "cct_store-outage-engineer"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def write_config(tmp: Path) -> Path:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "store" / "cell.db"), "backup_dir": str(tmp / "backups")}
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def stored_calibrations(config: CellConfig) -> list[int]:
    """An active camera and hand-eye calibration of cam0/robot0 (their content does not matter here)."""
    with open_store(config) as s:
        cam = s.save_calibration("camera", "cam0", None, {"model": "opencv5"}, {}, "test")
        he = s.save_calibration("handeye", "cam0", "robot0", {"setup": "eye-in-hand"}, {}, "test")
        s.activate(cam.id, "test")
        s.activate(he.id, "test")
        s.save_recipe(1, "bracket", {"models": {}}, "test")
    return [cam.id, he.id]


@pytest.fixture()
def damaged_app(tmp_path: Path) -> Iterator[tuple[TestClient, list[int], CellConfig]]:
    config = load_config(write_config(tmp_path))
    ids = stored_calibrations(config)
    damage_table(tmp_path / "store" / "cell.db", "calibrations")
    app = create_app(config, [("eng", "engineer", hash_token(TOKEN))])
    with TestClient(app) as client:
        yield client, ids, config


def test_routes_on_a_damaged_store_answer_503_with_the_restore_command(
        damaged_app: tuple[TestClient, list[int], CellConfig]) -> None:
    client, ids, config = damaged_app
    before = client.get("/health").json()
    assert before["store"] == {"available": True, "reason": None}  # nothing has read the damaged page yet
    answers = [client.get("/calibrations", headers=AUTH), client.get(f"/calibrations/{ids[0]}", headers=AUTH),
               client.post("/map", json={"u_px": 320, "v_px": 240, "plane_z_mm": 0}, headers=AUTH)]
    for r in answers:
        assert r.status_code == 503, r.text
        error = r.json()["error"]
        assert error["code"] == "store_unavailable"
        assert "cell.db is damaged (database disk image is malformed)" in error["message"]
        assert f"cellctl store restore --config {config.source} --latest --force" in error["message"]
    # What the damage did not reach still answers.
    assert client.get("/recipes", headers=AUTH).status_code == 200
    health = client.get("/health")
    assert health.status_code == 200
    body = health.json()
    assert body["store"]["available"] is False and "is damaged" in body["store"]["reason"]
    assert body["status"] == "store_unavailable"  # whether or not the warm-up is done


def _serve(config: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    """``cellctl serve`` that is expected to refuse before it serves: (exit code, stderr)."""
    capsys.readouterr()
    code = main(["serve", "--config", str(config), "--port", str(free_port()), *extra])
    return code, capsys.readouterr().err


def test_serve_refuses_a_damaged_or_lost_store_and_restoring_the_backup_brings_it_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_config(tmp_path)
    config = load_config(path)
    ids = stored_calibrations(config)
    db = tmp_path / "store" / "cell.db"
    served = start_served(tmp_path, path)  # the first start: the store is recorded
    try:
        listed = served.client().get("/calibrations")
        assert listed.status_code == 200 and [c["id"] for c in listed.json()] == ids
    finally:
        stop_served(served)
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))
    assert main(["store", "backup", "--config", str(path)]) == 0

    damage_table(db, "calibrations")
    code, err = _serve(path, capsys)
    assert code == 2 and "refusing to start: the store" in err and "is damaged" in err
    assert f"cellctl store restore --config {path} --latest --force" in err
    assert main(["store", "restore", "--config", str(path), "--latest", "--force"]) == 0

    served = start_served(tmp_path, path)
    try:
        listed = served.client().get("/calibrations")
        assert listed.status_code == 200 and [c["id"] for c in listed.json()] == ids
        assert served.client().get("/health").json()["store"]["available"] is True
    finally:
        stop_served(served)

    for side in ("-wal", "-shm"):
        db.with_name(db.name + side).unlink(missing_ok=True)
    db.write_bytes(b"")
    code, err = _serve(path, capsys)
    assert code == 2 and f"the store {db} is empty (0 bytes)" in err
    assert f"cellctl serve --config {path} --new-store" in err and db.stat().st_size == 0
    db.unlink()
    code, err = _serve(path, capsys)
    assert code == 2 and f"the store {db} does not exist" in err and not db.exists()


def test_stop_on_a_damaged_store_still_answers_that_the_robot_stopped(tmp_path: Path) -> None:
    """Stop always wins: the robot halts and latches; the store's failure shows as not stored, not as an error."""
    config = load_config(write_config(tmp_path))
    stored_calibrations(config)
    damage_table(tmp_path / "store" / "cell.db", "audit")
    app = create_app(config, [("eng", "engineer", hash_token(TOKEN))])
    with TestClient(app) as client:
        t0 = time.monotonic()
        r = client.post("/robots/robot0/stop", headers=AUTH)
        took_s = time.monotonic() - t0
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["stopped"] is True and body["latched"] is True
        assert body["audit_stored"] is False and body["latch_stored"] is False
        assert took_s < 4.0  # not the latch wait's 5 s: a failing store is answered at once
        assert client.get("/robots/robot0/state", headers=AUTH).json()["latched"] is True
