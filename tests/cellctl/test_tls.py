"""HTTPS: ``cellctl serve --tls-cert/--tls-key`` with a self-signed certificate made by openssl."""

from __future__ import annotations

import os
import ssl
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text
from tests.conftest import free_port
from tests.support.forked import popen_cellctl
from tests.support.wait import wait_until


def make_cert(folder: Path, name: str = "cell") -> tuple[Path, Path]:
    """A self-signed EC certificate for 127.0.0.1 (subjectAltName IP), and its key."""
    cert, key = folder / f"{name}-cert.pem", folder / f"{name}-key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
                    "-nodes", "-keyout", str(key), "-out", str(cert), "-days", "2", "-subj", "/CN=cellctl-test",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True, timeout=60)
    return cert, key


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return make_cert(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def https_cell(tmp_path_factory: pytest.TempPathFactory, certs: tuple[Path, Path]) -> Iterator[tuple[str, Path]]:
    tmp = tmp_path_factory.mktemp("https")
    cert, key = certs
    port = free_port()
    env = {**os.environ, "CELLCTL_DATA_DIR": str(tmp / "data")}
    log = (tmp / "serve.log").open("wb")
    proc = popen_cellctl(["serve", "--host", "127.0.0.1", "--port", str(port), "--tls-cert", str(cert),
                          "--tls-key", str(key)], env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"https://127.0.0.1:{port}"
    ctx = ssl.create_default_context(cafile=str(cert))
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, (tmp / "serve.log").read_text()
            try:
                if httpx.get(base + "/health", verify=ctx, timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                assert time.monotonic() < deadline, (tmp / "serve.log").read_text()
                time.sleep(0.2)
        yield base, tmp
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_health_over_https(https_cell: tuple[str, Path], certs: tuple[Path, Path]) -> None:
    base, tmp = https_cell
    ctx = ssl.create_default_context(cafile=str(certs[0]))
    with httpx.Client(verify=ctx, timeout=10) as c:
        r = c.get(base + "/health")
        assert r.status_code == 200 and r.json()["status"] in ("starting", "ok")
        wait_until(lambda: c.get(base + "/health").json()["status"] == "ok", 300, "the warm-up's end over HTTPS")
        token = next((tmp / "data").glob("*.session-token")).read_text().strip()
        r = c.get(base + "/robots/robot0/state", headers={"Authorization": f"Bearer {token}"})
        assert r.status_code == 200
    # the certificate really is the one presented: a client trusting another CA refuses the server
    other_cert, _ = make_cert(tmp, "other")
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(base + "/health", verify=ssl.create_default_context(cafile=str(other_cert)), timeout=10)
    # and the port speaks only TLS
    with pytest.raises(httpx.HTTPError):
        httpx.get(base.replace("https://", "http://") + "/health", timeout=5)


def run_serve(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``cellctl serve`` in process (these setups are refused before anything is served)."""
    code = main(["serve", "--host", "127.0.0.1", "--port", str(free_port()), *args])
    return code, capsys.readouterr().err


def test_bad_tls_setups_are_refused_with_one_line(tmp_path: Path, certs: tuple[Path, Path],
                                                  capsys: pytest.CaptureFixture[str],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELLCTL_DATA_DIR", str(tmp_path / "data"))
    cert, key = certs
    other_cert, other_key = make_cert(tmp_path, "other")
    cases = [
        (("--tls-cert", str(cert)), "TLS needs both a certificate and a key"),
        (("--tls-cert", str(cert), "--tls-key", str(tmp_path / "absent.pem")), "absent.pem: missing or not readable"),
        (("--tls-cert", str(cert), "--tls-key", str(other_key)), "cannot be used"),
        (("--tls-cert", str(tmp_path / "nope.pem"), "--tls-key", str(key)), "nope.pem: missing"),
    ]
    for args, expected in cases:
        code, err = run_serve(capsys, *args)
        assert code == 2, (args, err)
        assert expected in err and "Traceback" not in err, (args, err)
        assert err.startswith("cellctl: error:") and len(err.strip().splitlines()) == 1, err
    # an encrypted key is refused, never prompted for
    enc_key = tmp_path / "enc-key.pem"
    subprocess.run(["openssl", "pkey", "-in", str(other_key), "-aes256", "-passout", "pass:secret",
                    "-out", str(enc_key)], check=True, capture_output=True, timeout=60)
    code, err = run_serve(capsys, "--tls-cert", str(other_cert), "--tls-key", str(enc_key))
    assert code == 2 and "unencrypted PEM key" in err, err
    assert not (tmp_path / "data").exists()  # refused before anything was written


def test_config_keys_for_tls(tmp_path: Path, certs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    data = yaml.safe_load(default_config_text())
    data["http"]["tls_cert"] = str(certs[0])
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    assert main(["config", "check", "--config", str(tmp_path / "cell.yaml")]) == 2
    err = capsys.readouterr().err
    assert "http: " in err and "tls_cert and tls_key go together" in err
    data["http"]["tls_key"] = str(certs[1])
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(data))
    assert main(["config", "check", "--config", str(tmp_path / "cell.yaml")]) == 0, capsys.readouterr().err
