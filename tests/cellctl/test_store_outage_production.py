"""A damaged store answers 503 on the production routes too (issue 34: ``GET /production`` answered 500)."""

from __future__ import annotations

from pathlib import Path

import yaml
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.auth import hash_token
from cellctl.config import default_config_text, load_config
from cellctl.store import open_store
from tests.store.helpers import damage_table

TOKEN = "cct_store-outage-production"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def test_get_production_on_damaged_production_tables_is_503(tmp_path: Path) -> None:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path / "store" / "cell.db")}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    config = load_config(tmp_path / "cell.yaml")
    with open_store(config) as store:
        store.set_next_slot(1, 3, "test")
    damage_table(tmp_path / "store" / "cell.db", "production_runs")
    app = create_app(config, [("eng", "engineer", hash_token(TOKEN))])
    with TestClient(app) as client:
        for r in (client.get("/production", headers=AUTH), client.get("/production/runs/1/cycles", headers=AUTH)):
            assert r.status_code == 503, r.text
            err = r.json()["error"]
            assert err["code"] == "store_unavailable" and "is damaged" in err["message"], err
            assert "cellctl store restore" in err["message"]
