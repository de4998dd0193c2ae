"""A caller's ``X-Request-Id`` is echoed and logged only when it is a sane id with no credential in it
(issue 34, item 6): a bearer token put there is neither echoed nor written to the log."""

from __future__ import annotations

import io
import json
import logging

import pytest
import yaml
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.api.request_id import MAX_REQUEST_ID_CHARS, safe_request_id
from cellctl.auth import hash_token
from cellctl.config import default_config_text, parse_config
from cellctl.logging_setup import configure_logging

TOKEN = "cct_request-id-test-token-0123456789abcdef"
OTHER_SYSTEMS_TOKEN = "Zm9vYmFyYmF6cXV4cXV1eDAxMjM0NTY3ODk"  # a secret of the right form, known to the service


@pytest.mark.parametrize("value", ["rid-4711", "order-4711:step-3", "3f2b8c1e-0d9a-4c55-9e0b-6a7c1d2e3f40",
                                   "a" * MAX_REQUEST_ID_CHARS])
def test_a_sane_request_id_is_kept(value: str) -> None:
    assert safe_request_id(value) == value


@pytest.mark.parametrize("value", [
    "", "a" * (MAX_REQUEST_ID_CHARS + 1), "x" * 1_000_000, "two words", "line\nbreak", "tab\there", "é-accent",
    "<script>", "id;rm", TOKEN, "CCT_upper-case-prefix", "Bearer", "Bearer-" + TOKEN[4:], "basic:dXNlcjpwdw",
    "eyJhbGciOiJIUzI1NiJ9.eyJzdWIiOiIxIn0.c2lnbmF0dXJl",
])
def test_an_unsafe_request_id_is_refused(value: str) -> None:
    assert safe_request_id(value) is None


def test_a_token_the_service_knows_is_refused_whatever_its_form() -> None:
    known = {OTHER_SYSTEMS_TOKEN}
    assert safe_request_id(OTHER_SYSTEMS_TOKEN, lambda t: t if t in known else None) is None
    assert safe_request_id("an-ordinary-id-0001", lambda t: t if t in known else None) == "an-ordinary-id-0001"


@pytest.mark.parametrize("sent", [f"Bearer {TOKEN}", TOKEN, OTHER_SYSTEMS_TOKEN, "r" * 200])
def test_the_service_neither_echoes_nor_logs_a_credential_in_the_request_id(sent: str) -> None:
    data = yaml.safe_load(default_config_text())
    data["auth"]["tokens"] = [{"name": "e", "role": "engineer", "sha256": hash_token(TOKEN)},
                              {"name": "plc", "role": "viewer", "sha256": hash_token(OTHER_SYSTEMS_TOKEN)}]
    app = create_app(parse_config(data, "test"))

    def noisy() -> dict[str, str]:
        logging.getLogger("cellctl.test.rid").warning("inside the route")
        return {}

    app.add_api_route("/_noisy", noisy)
    buf = io.StringIO()
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging("json", stream=buf)
        r = TestClient(app).get("/_noisy", headers={"X-Request-Id": sent})
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
    assert r.status_code == 200
    echoed = r.headers["x-request-id"]
    assert echoed != sent and len(echoed) == 32 and all(c in "0123456789abcdef" for c in echoed)
    log = buf.getvalue()
    assert sent not in log and TOKEN not in log and OTHER_SYSTEMS_TOKEN not in log
    assert any(json.loads(line).get("request_id") == echoed for line in log.splitlines())
