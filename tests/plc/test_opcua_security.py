"""OPC UA with Basic256Sha256 refuses to start when no client certificate is trusted (``cellctl serve``).

Without a trust list asyncua accepts any self-signed client certificate, which could then call
``Pick``; the service must say how to trust one instead of starting open. Certificates are made
here (``make_cert``). The refusal without a trust list runs the real ``cellctl serve`` process (the
entry point: exit code, one line on stderr); the empty trust list runs the same ``main`` in this
process (``tests.support.cli.run_cli``: the same exit and output, without a new interpreter).
"""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from cellctl.config import ConfigError, default_config_text, parse_config
from tests.conftest import CELLCTL, free_port
from tests.plc.test_opcua_server import make_cert
from tests.support.cli import run_cli

HOW_TO_TRUST = "copy the client's application certificate there"


def secure_config(tmp: Path, trusted: Path | None) -> tuple[Path, int, int]:
    server_cert, server_key = make_cert(tmp / "pki" / "server", "cellctl", "urn:cellctl:virtual-cell", server=True)
    opcua: dict[str, Any] = {"enabled": True, "host": "127.0.0.1", "port": free_port(), "security": "basic256sha256",
                             "cert": str(server_cert), "key": str(server_key)}
    if trusted is not None:
        opcua["trusted_client_certs"] = str(trusted)
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    data["plc"] = {"opcua": opcua}
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, int(opcua["port"]), free_port()


def serve(tmp: Path, config: Path, http_port: int, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run ``cellctl serve`` expecting it to refuse; returns its exit and output."""
    env = {"CELLCTL_DATA_DIR": str(tmp / "data"), "PATH": "/usr/bin:/bin"}
    return subprocess.run([CELLCTL, "serve", "--config", str(config), "--port", str(http_port)],
                          capture_output=True, text=True, timeout=timeout_s, env=env)


def listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_the_config_refuses_basic256sha256_without_trusted_client_certs(tmp_path: Path) -> None:
    path, _, _ = secure_config(tmp_path, trusted=None)
    with pytest.raises(ConfigError) as e:
        parse_config(yaml.safe_load(path.read_text()))
    assert "plc.opcua" in str(e.value) and "trusted_client_certs" in str(e.value) and HOW_TO_TRUST in str(e.value)


def test_serve_refuses_to_start_without_trusted_client_certs(tmp_path: Path) -> None:
    path, opcua_port, http_port = secure_config(tmp_path, trusted=None)
    done = serve(tmp_path, path, http_port)
    assert done.returncode != 0
    assert "trusted_client_certs" in done.stderr and HOW_TO_TRUST in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr  # one clear line, not a stack
    assert not listening(opcua_port) and not listening(http_port)
    assert not list((tmp_path / "data").glob("*.session-token"))


def test_serve_refuses_to_start_with_an_empty_trusted_directory(tmp_path: Path) -> None:
    empty = tmp_path / "trusted"
    empty.mkdir()
    (empty / "README.txt").write_text("put the PLC's certificate here\n")
    path, opcua_port, http_port = secure_config(tmp_path, trusted=empty)
    env = {"CELLCTL_DATA_DIR": str(tmp_path / "data"), "PATH": "/usr/bin:/bin"}
    done = run_cli("serve", "--config", str(path), "--port", str(http_port), env=env)
    assert done.returncode != 0
    assert "holds no certificate" in done.stderr and HOW_TO_TRUST in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    assert not listening(opcua_port) and not listening(http_port)
    assert not list((tmp_path / "data").glob("*.session-token"))
