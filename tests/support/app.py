"""The service in the test process: the real app (``create_app``) behind FastAPI's ``TestClient``.

For the HTTP contract (auth, errors, validation, OpenAPI): the same routes, middleware, lifespan
(the cell's devices opened, the store), reached without a server process or a socket. What only a
real server shows (uvicorn's limits, floods, signals, slow clients) stays with ``start_served``.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.auth import hash_token, new_token
from cellctl.config import Role, load_config


@dataclass
class AppCell:
    """A running app: its client (no token by default), an engineer token, its data dir."""

    client: TestClient
    token: str
    data_dir: Path

    def auth(self, token: str | None = None) -> dict[str, str]:
        """The Authorization header for ``token`` (default: the engineer token)."""
        return {"Authorization": f"Bearer {token or self.token}"}

    def http(self, token: str | None = None) -> httpx.Client:
        """A client that sends ``token`` (default: the engineer's) with every request, like
        ``Served.client``; it shares the app's running lifespan with ``client``."""
        return httpx.Client(transport=self.client._transport, base_url=self.client.base_url,
                            headers=self.auth(token))


@contextmanager
def in_process_cell(tmp: Path, config: Path | None = None, token: str | None = None) -> Iterator[AppCell]:
    """The app for ``config`` (default: the built-in virtual cell) with its data in ``tmp/data``.

    As ``cellctl serve`` does, a config without tokens gets a one-run engineer token; give ``token``
    when the config holds tokens (it is then only what ``AppCell.auth()`` sends).
    """
    data = tmp / "data"
    saved = os.environ.get("CELLCTL_DATA_DIR")
    os.environ["CELLCTL_DATA_DIR"] = str(data)
    try:
        cfg = load_config(str(config) if config is not None else None)
        session: list[tuple[str, Role, str]] = []
        if not cfg.auth.tokens:
            token = new_token()
            session.append(("session", "engineer", hash_token(token)))
        if token is None:
            raise ValueError("the config holds tokens: give in_process_cell the one to use")
        app = create_app(cfg, session)
        with TestClient(app, base_url="http://127.0.0.1") as client:
            yield AppCell(client, token, data)
    finally:
        if saved is None:
            os.environ.pop("CELLCTL_DATA_DIR", None)
        else:
            os.environ["CELLCTL_DATA_DIR"] = saved
