"""The session-token file of ``cellctl serve`` (no tokens configured) is private whatever was there before.

A real ``cellctl serve`` of the virtual cell on loopback; the file is prepared as an older run or
a careless user may have left it: mode 644 with an old token, or a symlink to another file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import httpx

from tests.conftest import start_served, stop_served

TOKEN_FILE = "virtual-cell.session-token"


def mode(path: Path) -> int:
    return stat.S_IMODE(path.lstat().st_mode)


def test_an_old_world_readable_token_file_is_rewritten_with_mode_600(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    old = data / TOKEN_FILE
    old.write_text("cct_old-token-of-an-earlier-run\n")
    os.chmod(old, 0o644)
    served = start_served(tmp_path)
    try:
        assert mode(old) == 0o600 and old.is_file() and not old.is_symlink()
        token = old.read_text().strip()
        assert token != "cct_old-token-of-an-earlier-run" and token == served.token
        assert httpx.get(served.base_url + "/auth/whoami", headers={"Authorization": f"Bearer {token}"},
                         timeout=20).status_code == 200
        assert httpx.get(served.base_url + "/auth/whoami", timeout=20,
                         headers={"Authorization": "Bearer cct_old-token-of-an-earlier-run"}).status_code == 401
        assert not [p for p in data.iterdir() if p.name.endswith(".tmp")]  # no temporary left behind
    finally:
        stop_served(served)


def test_a_symlinked_token_file_is_replaced_not_followed(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("not yours\n")
    os.chmod(elsewhere, 0o644)
    (data / TOKEN_FILE).symlink_to(elsewhere)
    served = start_served(tmp_path)
    try:
        path = data / TOKEN_FILE
        assert not path.is_symlink() and mode(path) == 0o600 and path.read_text().strip() == served.token
        assert elsewhere.read_text() == "not yours\n" and mode(elsewhere) == 0o644
    finally:
        stop_served(served)
