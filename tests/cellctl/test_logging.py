"""Structured logs: one JSON object per line with the request id, from the real service."""

from __future__ import annotations

import io
import json
import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.auth import hash_token
from cellctl.config import default_config_text, parse_config
from cellctl.logging_setup import JsonFormatter, configure_logging, request_id_var
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    # stdout/stderr go to a file (not a terminal): the default format is JSON
    s = start_served(tmp_path_factory.mktemp("logging"))
    try:
        yield s
    finally:
        stop_served(s)


def json_lines(log_file: Path) -> list[dict[str, Any]]:
    out = []
    for line in log_file.read_text().splitlines():
        if line.startswith("{"):
            out.append(json.loads(line))  # every record line must be one complete JSON object
    return out


def test_service_logs_json_lines_with_request_id(served: Served) -> None:
    with served.client() as c:
        r = c.get("/robots/robot0/state", headers={"X-Request-Id": "log-test-1"})
        assert r.status_code == 200
        made = c.get("/health").headers["x-request-id"]
    log_file = served.data_dir.parent / "serve.log"
    records: list[dict[str, Any]] = []
    for _ in range(50):  # the access line is written as the response completes
        records = json_lines(log_file)
        if any(rec.get("request_id") == made for rec in records):
            break
        threading.Event().wait(0.1)
    lines = [ln for ln in log_file.read_text().splitlines() if ln.strip()]
    # apart from the session-token banner (plain stderr text for the person starting the service),
    # every line is a JSON record
    banner = [ln for ln in lines if not ln.startswith("{")]
    assert len(banner) <= 2 and all("token" in ln or ln.startswith("cct_") for ln in banner), banner
    for rec in records:
        assert {"time", "level", "logger", "message"} <= rec.keys()
        assert rec["time"].endswith("Z") and rec["level"] in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
    access = [rec for rec in records if rec.get("request_id") == "log-test-1"]
    assert len(access) == 1
    rec = access[0]
    assert rec["logger"] == "cellctl.access" and rec["status"] == 200 and rec["method"] == "GET"
    assert rec["path"] == "/robots/robot0/state" and rec["route"] == "/robots/{robot_id}/state"
    assert rec["duration_ms"] > 0
    assert any(r.get("request_id") == made and r["path"] == "/health" for r in records)
    # start-up records (no request) have no request id
    opened = [r for r in records if r["logger"] == "cellctl.api.app" and " open: " in r["message"]]
    assert opened and "request_id" not in opened[0]


def test_request_id_reaches_logs_written_inside_a_route() -> None:
    """A sync route runs in a worker thread: the id must follow it there."""
    data = yaml.safe_load(default_config_text())
    data["auth"]["tokens"] = [{"name": "e", "role": "engineer", "sha256": hash_token("cct_logging-test-token")}]
    app = create_app(parse_config(data, "test"))
    route_log = logging.getLogger("cellctl.test.route")

    def noisy() -> dict[str, str]:
        route_log.warning("inside the route", extra={"part": "A-17"})
        return {"thread": threading.current_thread().name}

    app.add_api_route("/_noisy", noisy)
    buf = io.StringIO()
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging("json", stream=buf)
        with TestClient(app) as client:
            r = client.get("/_noisy", headers={"X-Request-Id": "inner-9"})
        assert r.status_code == 200 and r.headers["x-request-id"] == "inner-9"
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
    records = [json.loads(line) for line in buf.getvalue().splitlines()]
    inner = [rec for rec in records if rec["logger"] == "cellctl.test.route"]
    assert len(inner) == 1
    assert inner[0]["request_id"] == "inner-9" and inner[0]["part"] == "A-17" and inner[0]["level"] == "WARNING"
    assert r.json()["thread"] != threading.current_thread().name


def test_json_formatter_keeps_a_record_on_one_line() -> None:
    logger = logging.getLogger("cellctl.test.fmt")
    buf = io.StringIO()
    handler = logging.StreamHandler(buf)
    handler.setFormatter(JsonFormatter())
    logger.addHandler(handler)
    logger.propagate = False
    logger.setLevel(logging.INFO)
    try:
        token = request_id_var.set("r-1")
        try:
            raise RuntimeError("camera cam0 vanished\nsecond line")
        except RuntimeError:
            logger.exception("grab failed for %s", "cam0", extra={"camera": "cam0", "attempt": 3})
        finally:
            request_id_var.reset(token)
        logger.info("no request")
    finally:
        logger.removeHandler(handler)
        logger.propagate = True
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2
    first, second = json.loads(lines[0]), json.loads(lines[1])
    assert first["message"] == "grab failed for cam0" and first["request_id"] == "r-1"
    assert first["camera"] == "cam0" and first["attempt"] == 3 and first["level"] == "ERROR"
    assert "RuntimeError: camera cam0 vanished\nsecond line" in first["exc"]
    assert "request_id" not in second


def test_text_format_shows_the_request_id() -> None:
    buf = io.StringIO()
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging("text", stream=buf)
        token = request_id_var.set("txt-5")
        logging.getLogger("cellctl.test.text").info("hello")
        request_id_var.reset(token)
        logging.getLogger("cellctl.test.text").info("outside")
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
    lines = buf.getvalue().splitlines()
    assert "INFO" in lines[0] and "[txt-5] hello" in lines[0] and "cellctl.test.text" in lines[0]
    assert "[-] outside" in lines[1]


def test_serve_refuses_an_unknown_log_format() -> None:
    r = run_cellctl("serve", "--log-format", "xml", timeout=60)
    assert r.returncode == 2
    assert "--log-format" in r.stderr and "invalid choice" in r.stderr and "Traceback" not in r.stderr
