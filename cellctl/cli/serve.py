"""``cellctl serve``: the REST service (the built-in virtual cell when no config is given)."""

from __future__ import annotations

import argparse
import logging
import os
import socket
import ssl
import sys
from pathlib import Path
from typing import Any

from cellctl.auth import hash_token, new_token
from cellctl.cli.output import CommandError
from cellctl.config import CellConfig, load_config
from cellctl.logging_setup import configure_logging
from cellctl.paths import data_dir

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("serve", help="run the REST service")
    p.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    p.add_argument("--host", help="bind address (default: the config's http.host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default: the config's http.port, 8080)")
    p.add_argument("--tls-cert", help="PEM certificate for HTTPS (default: the config's http.tls_cert; "
                                      "documented place: /etc/cellctl/tls/cert.pem)")
    p.add_argument("--tls-key", help="PEM private key for HTTPS (default: the config's http.tls_key; "
                                     "documented place: /etc/cellctl/tls/key.pem)")
    p.add_argument("--log-format", choices=("json", "text"), default=None,
                   help="log lines as JSON objects or text (default: text on a terminal, json otherwise)")
    p.add_argument("--new-store", action="store_true",
                   help="start even though the store is missing or empty while this cell ran on one before: "
                        "begins a new empty store (see docs/store.md)")
    p.set_defaults(func=run)


def session_token_file(config: CellConfig) -> Path:
    return data_dir() / f"{config.cell_id}.session-token"


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable and writable by this user only (mode 600).

    Written to a new file and renamed over ``path``: an old file keeps neither its mode (a 644
    token file becomes 600) nor its contents, and a symlink at ``path`` is replaced, not followed.
    """
    from cellctl.store.files import private_dir

    private_dir(path.parent)  # the data folder, 0700 when we create it
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def run(args: argparse.Namespace) -> None:
    import uvicorn

    from cellctl.api.app import create_app
    from cellctl.plc import preflight as plc_preflight
    from cellctl.store.startup import check_store_at_start

    config = load_config(args.config)
    http = config.http.model_copy(update={k: v for k, v in (("host", args.host), ("port", args.port),
                                                            ("tls_cert", args.tls_cert), ("tls_key", args.tls_key))
                                          if v})
    _check_tls(http.tls_cert, http.tls_key)
    config = config.model_copy(update={"http": http})
    _check_ports(config)  # before the session-token file: a serve that cannot start must not replace it
    plc_preflight(config)  # OPC UA certificates and the trusted clients: one line, not a start-up traceback
    check_store_at_start(config, new_store=args.new_store)  # damaged, missing or emptied store: refused
    session: list[tuple[str, Any, str]] = []
    if not config.auth.tokens:
        if not http.is_loopback():
            raise CommandError(f"refusing to serve on {http.host} with no tokens configured: add one with "
                               "`cellctl token add --config cell.yaml --name NAME --role engineer`, or bind 127.0.0.1")
        # Lab mode on loopback: a one-run engineer token, shown once and kept in a private file.
        token = new_token()
        path = session_token_file(config)
        write_private(path, token + "\n")
        session.append(("session", "engineer", hash_token(token)))
        print(f"cellctl: no tokens in the config; this run's engineer token (also in {path}):\n{token}",
              file=sys.stderr, flush=True)
    configure_logging(args.log_format, logging.DEBUG if getattr(args, "verbose", False) else logging.INFO)
    if http.tls_cert is None and not http.is_loopback():
        log.warning("serving plain HTTP on %s: tokens cross the network in clear; set http.tls_cert/tls_key",
                    http.host)
    from cellctl.api.app import ACCEPT_BACKLOG, guarded_protocol, raise_open_files_limit

    soft = raise_open_files_limit()  # descriptors for many clients; a cap and a reserve below (api/connections.py)
    protocol = guarded_protocol(http, soft)
    log.info("HTTP: at most %d connections (%d per address; open-files limit %d), request headers within %g s",
             protocol.guard.max_connections, protocol.guard.max_per_address, soft, protocol.guard.header_timeout_s)
    app = create_app(config, session)
    # Our handler formats uvicorn's records too (log_config=None); the middleware writes the access
    # log with the request id, so uvicorn's own access log is off.
    uvicorn.run(app, host=http.host, port=http.port, log_level="info", log_config=None, access_log=False,
                ssl_certfile=http.tls_cert, ssl_keyfile=http.tls_key, http=protocol, backlog=ACCEPT_BACKLOG)


def _check_ports(config: CellConfig) -> None:
    """Refuse, with one line, to start when a port the service must listen on is taken.

    (uvicorn and the PLC servers would otherwise fail half-way through start-up with a traceback.)
    """
    wanted = [("HTTP", config.http.host, config.http.port)]
    plc = config.plc
    if plc.modbus.enabled:
        wanted.append(("Modbus TCP (plc.modbus)", plc.modbus.host, plc.modbus.port))
    if plc.opcua.enabled:
        wanted.append(("OPC UA (plc.opcua)", plc.opcua.host, plc.opcua.port))
    for what, host, port in wanted:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError as exc:
                raise CommandError(f"cannot listen for {what} on {host}:{port} ({exc.strerror}); stop what "
                                   "uses that port or choose another one in the config") from None


def _check_tls(cert: str | None, key: str | None) -> None:
    """Refuse a half or unusable TLS setup with one clear line (uvicorn would print a traceback)."""
    if cert is None and key is None:
        return
    if cert is None or key is None:
        raise CommandError("TLS needs both a certificate and a key: give --tls-cert and --tls-key "
                           "(or http.tls_cert and http.tls_key in the config)")
    for what, path in (("certificate", cert), ("key", key)):
        if not os.access(path, os.R_OK):
            raise CommandError(f"TLS {what} {path}: missing or not readable by this user; "
                               "check the path and its permissions")
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key, password=_no_password)
    except (ssl.SSLError, ValueError) as exc:
        raise CommandError(f"TLS certificate {cert} with key {key} cannot be used ({exc}); "
                           "give a PEM certificate and its matching unencrypted PEM key") from None


def _no_password() -> str:
    """An encrypted key is refused, never prompted for (the service runs unattended)."""
    return ""
