"""Tokens in a running service: removal and addition take effect without a restart; a second
``cellctl serve`` on a taken port leaves the running server's session-token file alone."""

from __future__ import annotations

import contextlib
import io
import json
import os
import time
from pathlib import Path

import httpx
import pytest

from cellctl.cli import main
from cellctl.config import default_config_text
from tests.conftest import start_served, stop_served
from tests.support.forked import run_cellctl


def _cli(*args: str) -> dict[str, object]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(list(args)) == 0
    result: dict[str, object] = json.loads(out.getvalue())
    return result


def _status_becomes(base: str, token: str, want: int, timeout_s: float = 10.0) -> int:
    """Poll /auth/whoami until it answers ``want`` (the service notices the file change on a request)."""
    deadline = time.monotonic() + timeout_s
    status = -1
    while time.monotonic() < deadline:
        status = httpx.get(base + "/auth/whoami", headers={"Authorization": f"Bearer {token}"}).status_code
        if status == want:
            break
        time.sleep(0.05)
    return status


def test_remove_and_add_take_effect_without_restart(tmp_path: Path) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(default_config_text())
    keep = str(_cli("token", "add", "--config", str(cfg), "--name", "keep", "--role", "engineer")["token"])
    plc = str(_cli("token", "add", "--config", str(cfg), "--name", "plc", "--role", "operator")["token"])
    served = start_served(tmp_path, config=cfg, token=keep)
    try:
        assert not list((tmp_path / "data").glob("*.session-token"))  # tokens configured: no session token
        base = served.base_url
        assert _status_becomes(base, plc, 200) == 200
        assert _cli("token", "list", "--config", str(cfg))["tokens"] == [
            {"name": "keep", "role": "engineer"}, {"name": "plc", "role": "operator"}]
        _cli("token", "remove", "--config", str(cfg), "--name", "plc")
        assert _status_becomes(base, plc, 401) == 401
        r = httpx.get(base + "/auth/whoami", headers={"Authorization": f"Bearer {keep}"})
        assert r.status_code == 200 and r.json() == {"name": "keep", "role": "engineer"}
        late = str(_cli("token", "add", "--config", str(cfg), "--name", "late", "--role", "viewer")["token"])
        assert _status_becomes(base, late, 200) == 200
        # A broken edit by hand keeps the tokens the service had (and says so in its log).
        good_text = cfg.read_text()
        cfg.write_text(good_text + "robots: {oops\n")
        r = httpx.get(base + "/auth/whoami", headers={"Authorization": f"Bearer {late}"})
        assert r.status_code == 200
        cfg.write_text(good_text)
    finally:
        stop_served(served)
    log = (tmp_path / "serve.log").read_text()
    assert "does not validate; keeping the previous tokens" in log


def test_serve_on_a_taken_port_keeps_the_session_token(tmp_path: Path) -> None:
    served = start_served(tmp_path)
    try:
        token_file, = (tmp_path / "data").glob("*.session-token")
        before = token_file.read_text()
        assert before.strip() == served.token
        port = served.base_url.rsplit(":", 1)[1]
        env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp_path / "data")}
        r = run_cellctl("serve", "--host", "127.0.0.1", "--port", port, env=env, timeout=60)
        assert r.returncode != 0
        assert f"127.0.0.1:{port}" in r.stderr and "Traceback" not in r.stderr
        assert token_file.read_text() == before
        r2 = httpx.get(served.base_url + "/auth/whoami", headers={"Authorization": f"Bearer {served.token}"})
        assert r2.status_code == 200
    finally:
        stop_served(served)


@pytest.mark.parametrize("name", ["nobody"])
def test_remove_of_an_unknown_name_names_the_configured_ones(tmp_path: Path, name: str) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(default_config_text())
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["token", "remove", "--config", str(cfg), "--name", name]) != 0
    assert f"no token named {name!r}; configured: none" in err.getvalue()
