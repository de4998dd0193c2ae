"""``cellctl serve``: the REST service (the built-in virtual cell when no config is given)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any

from cellctl.auth import hash_token, new_token
from cellctl.cli.output import CommandError
from cellctl.config import CellConfig, load_config
from cellctl.paths import data_dir

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("serve", help="run the REST service")
    p.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    p.add_argument("--host", help="bind address (default: the config's http.host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default: the config's http.port, 8080)")
    p.set_defaults(func=run)


def session_token_file(config: CellConfig) -> Path:
    return data_dir() / f"{config.cell_id}.session-token"


def run(args: argparse.Namespace) -> None:
    import uvicorn

    from cellctl.api.app import create_app

    config = load_config(args.config)
    http = config.http.model_copy(update={k: v for k, v in (("host", args.host), ("port", args.port)) if v})
    config = config.model_copy(update={"http": http})
    session: list[tuple[str, Any, str]] = []
    if not config.auth.tokens:
        if not http.is_loopback():
            raise CommandError(f"refusing to serve on {http.host} with no tokens configured: add one with "
                               "`cellctl token add --config cell.yaml --name NAME --role engineer`, or bind 127.0.0.1")
        # Lab mode on loopback: a one-run engineer token, shown once and kept in a private file.
        token = new_token()
        path = session_token_file(config)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        session.append(("session", "engineer", hash_token(token)))
        print(f"cellctl: no tokens in the config; this run's engineer token (also in {path}):\n{token}",
              file=sys.stderr, flush=True)
    app = create_app(config, session)
    uvicorn.run(app, host=http.host, port=http.port, log_level="info")
