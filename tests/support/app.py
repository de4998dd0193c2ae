"""The service in the test process: the real app (``create_app``) behind FastAPI's ``TestClient``.

For the HTTP contract (auth, errors, validation, OpenAPI): the same routes, middleware, lifespan
(the cell's devices opened, the store), reached without a server process or a socket. What only a
real server shows (uvicorn's limits, floods, signals, slow clients) stays with ``start_served``.

``served_in_thread`` is between the two: uvicorn serving the same app on a loopback port from a
thread of this process, for a client that needs a URL (the ``cellctl job`` CLI as a subprocess, a
streamed response read as a real client reads it) without paying a new interpreter, its imports
and its warm-up.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
from fastapi import FastAPI
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.auth import hash_token, new_token
from cellctl.config import Role, load_config
from drivers.sim.world import forget_worlds
from tests.support.served import Reachable


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
def _data_dir(data: Path) -> Iterator[None]:
    """``CELLCTL_DATA_DIR`` set to ``data`` for the block, as ``cellctl serve`` would see it."""
    saved = os.environ.get("CELLCTL_DATA_DIR")
    os.environ["CELLCTL_DATA_DIR"] = str(data)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("CELLCTL_DATA_DIR", None)
        else:
            os.environ["CELLCTL_DATA_DIR"] = saved


def _app_for(config: Path | None, token: str | None) -> tuple[FastAPI, str]:
    """The app for ``config`` and the engineer token it accepts (a one-run one when it holds none).

    The built-in virtual cell's world starts afresh, as in a new ``cellctl serve``: an earlier in-process
    cell of the same worker may have left its robot elsewhere, and the virtual cell's camera rides on the
    robot (a teach ROI then showed no part). Worlds of scene files are kept: a test may set one up before
    its cell (the UR emulator's mirror of the arm)."""
    forget_worlds(None, only_that_scene=True)
    cfg = load_config(str(config) if config is not None else None)
    session: list[tuple[str, Role, str]] = []
    if not cfg.auth.tokens:
        token = new_token()
        session.append(("session", "engineer", hash_token(token)))
    if token is None:
        raise ValueError("the config holds tokens: give the token to use")
    return create_app(cfg, session), token


@contextmanager
def in_process_cell(tmp: Path, config: Path | None = None, token: str | None = None) -> Iterator[AppCell]:
    """The app for ``config`` (default: the built-in virtual cell) with its data in ``tmp/data``.

    As ``cellctl serve`` does, a config without tokens gets a one-run engineer token; give ``token``
    when the config holds tokens (it is then only what ``AppCell.auth()`` sends).
    """
    data = tmp / "data"
    with _data_dir(data):
        app, token = _app_for(config, token)
        with TestClient(app, base_url="http://127.0.0.1") as client:
            yield AppCell(client, token, data)


class ThreadServed(Reachable):
    """The app served by uvicorn from a thread of this process: its base URL, engineer token, data dir."""


@contextmanager
def served_in_thread(tmp: Path, config: Path | None = None, token: str | None = None,
                     timeout_s: float = 120.0) -> Iterator[ThreadServed]:
    """Serve the app for ``config`` (default: the virtual cell) on a free 127.0.0.1 port from a thread,
    its data in ``tmp/data``; ready once ``/health`` no longer says ``starting`` (the warm-up is done).

    Not a process: no signals, no exit code, no session-token file; use ``start_served`` for those.
    """
    import uvicorn

    from tests.support.ports import free_port

    data = tmp / "data"
    with _data_dir(data):
        app, token = _app_for(config, token)
        port = free_port()
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None,
                                               access_log=False, lifespan="on"))
        thread = threading.Thread(target=server.run, name=f"uvicorn-{port}", daemon=True)
        thread.start()
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                if not thread.is_alive():
                    raise RuntimeError(f"the app served on port {port} stopped while starting")
                try:
                    if httpx.get(base + "/health", timeout=2.0).json().get("status") not in (None, "starting"):
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the app served on port {port} was not ready within {timeout_s} s")
                time.sleep(0.05)
            yield ThreadServed(base, token, data)
        finally:
            server.should_exit = True
            thread.join(30.0)
