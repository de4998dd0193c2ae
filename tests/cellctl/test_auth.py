"""The auth matrix: each route x each role x no/bad token, on the app (in-process) with three tokens."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cellctl.cli import main
from tests.support.app import AppCell, in_process_cell

ROLES = ("viewer", "operator", "engineer")
RANK = {r: i for i, r in enumerate(ROLES)}

# (method, path, body, least role). Bodies are valid enough to get past auth; the status for an
# allowed role may be 2xx, 404, 409 or 422 — never 401/403 — depending on the cell's state.
ROUTES: list[tuple[str, str, dict[str, Any] | None, str]] = [
    ("GET", "/auth/whoami", None, "viewer"),
    ("GET", "/cameras", None, "viewer"),
    ("GET", "/cameras/cam0/settings", None, "viewer"),
    ("GET", "/cameras/cam0/image", None, "viewer"),
    ("GET", "/robots", None, "viewer"),
    ("GET", "/robots/robot0/state", None, "viewer"),
    ("POST", "/robots/robot0/move", {"pose_ur": {"x_m": 9, "y_m": 0, "z_m": 0.3, "rx_rad": 3.14, "ry_rad": 0,
                                                 "rz_rad": 0}}, "engineer"),
    ("POST", "/robots/robot0/stop", None, "operator"),
    ("GET", "/targets", None, "viewer"),
    ("GET", "/targets/plate", None, "viewer"),
    ("GET", "/calibrations", None, "viewer"),
    ("GET", "/calibrations/999", None, "viewer"),
    ("POST", "/calibrations/999/activate", None, "engineer"),
    ("POST", "/calibrations/rollback", {"kind": "camera", "camera_id": "cam0"}, "engineer"),
    ("GET", "/calibrations/999/export", None, "viewer"),
    ("GET", "/routines", None, "viewer"),
    ("POST", "/routines/verify", {}, "operator"),
    ("POST", "/routines/intrinsics-capture", {"views": "bad"}, "engineer"),
    ("GET", "/jobs", None, "viewer"),
    ("GET", "/jobs/nosuchjob", None, "viewer"),
    ("DELETE", "/jobs/nosuchjob", None, "operator"),
    ("POST", "/jobs/nosuchjob/record", None, "operator"),
    ("POST", "/map", {"u_px": 1, "v_px": 2}, "viewer"),
    ("GET", "/recipes", None, "viewer"),
    ("POST", "/recipes", {"recipe_id": 1, "recipe": {"name": "x", "models": [{}]}}, "engineer"),
    ("POST", "/pick", {"recipe_id": 77}, "operator"),
    ("POST", "/pick", {"recipe_id": 77, "move": True}, "engineer"),
    ("POST", "/pick/teach", {"roi": [-5, 0, 10, 10]}, "engineer"),
    ("GET", "/frames/999.png", None, "viewer"),
    ("GET", "/audit", None, "engineer"),
    ("GET", "/drift", None, "viewer"),
    ("POST", "/drift/check", None, "operator"),
    ("POST", "/drift/resolve", None, "engineer"),
    ("POST", "/sim/faults", {}, "engineer"),
]


@pytest.fixture(scope="module")
def cell_with_tokens(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("auth")
    cfg = tmp / "cell.yaml"
    from cellctl.config import default_config_text

    cfg.write_text(default_config_text())
    tokens: dict[str, str] = {}
    for role in ROLES:
        out = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-1", "--role", role,
                     "--out", str(out)]) == 0
        tokens[role] = json.loads(out.read_text())["token"]
    assert tokens["viewer"] not in cfg.read_text()  # stored hashed only
    with in_process_cell(tmp, config=cfg, token=tokens["engineer"]) as cell:
        yield cell, tokens


@pytest.mark.parametrize(("method", "path", "body", "least"), ROUTES, ids=[f"{m} {p}" for m, p, _, _ in ROUTES])
def test_auth_matrix(cell_with_tokens: tuple[AppCell, dict[str, str]], method: str, path: str,
                     body: dict[str, Any] | None, least: str) -> None:
    cell, tokens = cell_with_tokens
    http = cell.client
    r = http.request(method, path, json=body)
    assert r.status_code == 401, (method, path, r.status_code)
    r = http.request(method, path, json=body, headers={"Authorization": "Bearer not-a-token"})
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"
    for role in ROLES:
        r = http.request(method, path, json=body, headers={"Authorization": f"Bearer {tokens[role]}"})
        if RANK[role] < RANK[least]:
            assert r.status_code == 403, (method, path, role, r.status_code, r.text)
            assert r.json()["error"]["code"] == "forbidden"
        else:
            assert r.status_code not in (401, 403, 500), (method, path, role, r.status_code, r.text)


def test_open_routes_need_no_token(cell_with_tokens: tuple[AppCell, dict[str, str]]) -> None:
    cell, _ = cell_with_tokens
    for path in ("/health", "/openapi.json", "/docs", "/redoc", "/docs/assets/swagger-ui-bundle.js", "/",
                 "/ui/main.js"):
        assert cell.client.get(path).status_code == 200


def test_refuses_non_loopback_without_tokens(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["serve", "--host", "0.0.0.0", "--port", "1"]) == 2
    assert "refusing to serve on 0.0.0.0 with no tokens configured" in capsys.readouterr().err
