"""The service's edge, in process: who may send a body, how long it may take, what it may hold.

The app of ``create_app`` is called as an ASGI app with a ``receive`` that records whether the
body was asked for (the edge must refuse a caller without reading it), that trickles it, or that
leaves mid-body. Routes that need the live cell run under ``TestClient`` (the virtual cell in
this process); what a real server adds (uvicorn closing connections, floods) is in
tests/cellctl/test_floods.py.
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import Iterator, MutableMapping
from pathlib import Path
from typing import Any

import anyio.to_thread
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from cellctl.api.app import create_app
from cellctl.api.body import MAX_DEPTH, MAX_NUMBER_CHARS, MAX_VALUES
from cellctl.auth import hash_token
from cellctl.config import CellConfig, load_config
from cellctl.pick.model import teach
from tests.support.wait import wait_until

TOKENS = {"viewer": "cct_edge-viewer", "operator": "cct_edge-operator", "engineer": "cct_edge-engineer"}


def make_app(tmp: Path, body_timeout_s: float = 5.0) -> FastAPI:
    cfg: CellConfig = load_config(None)
    cfg = cfg.model_copy(update={"store": cfg.store.model_copy(update={"path": str(tmp / "cell.db")}),
                                 "http": cfg.http.model_copy(update={"body_timeout_s": body_timeout_s})})
    return create_app(cfg, [(role, role, hash_token(t)) for role, t in TOKENS.items()])  # type: ignore[misc]


def auth(role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[role]}"}


class Exchange:
    """One request sent straight to the ASGI app; records what the app asked of ``receive``."""

    def __init__(self, chunks: list[bytes], gap_s: float = 0.0, leave_after: int | None = None,
                 stall_after: int | None = None) -> None:
        self.chunks, self.gap_s, self.leave_after = chunks, gap_s, leave_after
        self.stall_after = len(chunks) if stall_after is None else stall_after
        self.reads = 0
        self.status: int | None = None
        self.headers: dict[str, str] = {}
        self.body = b""

    async def receive(self) -> dict[str, Any]:
        self.reads += 1
        if self.leave_after is not None and self.reads > self.leave_after:
            return {"type": "http.disconnect"}
        if self.reads > self.stall_after:
            await asyncio.sleep(3600)  # the client sends nothing more
        await asyncio.sleep(self.gap_s)
        return {"type": "http.request", "body": self.chunks[self.reads - 1], "more_body": self.reads < len(self.chunks)}

    async def send(self, message: MutableMapping[str, Any]) -> None:
        if message["type"] == "http.response.start":
            self.status = message["status"]
            self.headers = {k.decode().lower(): v.decode() for k, v in message["headers"]}
        elif message["type"] == "http.response.body":
            self.body += message.get("body", b"")


def call(app: FastAPI, method: str, path: str, headers: dict[str, str], ex: Exchange,
         declared: int | None = None) -> Exchange:
    length = declared if declared is not None else sum(len(c) for c in ex.chunks)
    raw = [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    raw += [(b"content-type", b"application/json"), (b"content-length", str(length).encode())]
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "path": path,
             "raw_path": path.encode(), "root_path": "", "scheme": "http", "query_string": b"", "headers": raw,
             "client": ("127.0.0.1", 5000), "server": ("127.0.0.1", 8080)}
    asyncio.run(asyncio.wait_for(app(scope, ex.receive, ex.send), 30.0))
    return ex


def counted(app: FastAPI, status: int) -> float:
    """Requests counted with ``status`` in the app's latency histogram (any route)."""
    text = app.state.metrics.render().decode()
    return sum(float(m.group(1)) for m in re.finditer(
        rf'cellctl_http_request_duration_seconds_count{{[^}}]*status="{status}"[^}}]*}} ([0-9.e+]+)', text))


# -- no body is read before its caller is known ---------------------------------------------------------

BIG = b"[" + b"1e300," * 1_000_000 + b"1]"  # ~6 MB of numbers that cost a parse


@pytest.fixture(scope="module")
def edge_app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    """One app for the refusals that keep no state (no body read, a shape refused): an app and its route
    table cost about 0.15 s of CPU each. The tests that count requests in the app's metrics make their own."""
    return make_app(tmp_path_factory.mktemp("edge-refusals"))


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer not-a-token"}, {"Authorization": "Basic eDp5"}],
                         ids=["no token", "unknown token", "not bearer"])
def test_a_caller_without_a_valid_token_is_refused_before_its_body_is_read(edge_app: FastAPI,
                                                                           headers: dict[str, str]) -> None:
    ex = call(edge_app, "POST", "/robots/robot0/stop", headers, Exchange([BIG]))
    assert ex.status == 401 and ex.reads == 0
    assert ex.headers["connection"] == "close"  # the server drops the unread body instead of draining it
    assert json.loads(ex.body)["error"]["code"] == "unauthorized"


def test_a_role_too_low_is_refused_before_its_body_is_read(edge_app: FastAPI) -> None:
    ex = call(edge_app, "POST", "/recipes", auth("operator"), Exchange([BIG]))
    assert ex.status == 403 and ex.reads == 0 and ex.headers["connection"] == "close"
    assert "engineer" in json.loads(ex.body)["error"]["message"]


def test_an_open_route_never_reads_a_body(edge_app: FastAPI) -> None:
    ex = call(edge_app, "POST", "/health", {}, Exchange([BIG]))
    assert ex.status == 405 and ex.reads == 0 and ex.headers["connection"] == "close"


# -- slow bodies and clients that leave -----------------------------------------------------------------

def test_a_slow_body_times_out_with_408_not_500(tmp_path: Path) -> None:
    app = make_app(tmp_path, body_timeout_s=0.3)
    ex = call(app, "POST", "/map", auth("viewer"), Exchange([b'{"u_px": 1', b', "v_px": 2}'], gap_s=0.2),
              declared=23)
    assert ex.status == 408 and ex.headers["connection"] == "close"
    body = json.loads(ex.body)["error"]
    assert body["code"] == "body_timeout" and "http.body_timeout_s" in body["message"]
    # A body that never completes (the client stops sending) times out the same way.
    ex = call(app, "POST", "/map", auth("viewer"), Exchange([b'{"u_px": 1', b"}"], stall_after=1), declared=23)
    assert ex.status == 408
    assert counted(app, 408) == 2 and counted(app, 500) == 0


def test_a_client_that_leaves_mid_body_is_a_client_error(tmp_path: Path) -> None:
    app = make_app(tmp_path)
    ex = call(app, "POST", "/map", auth("viewer"), Exchange([b'{"u_px": 1', b"", b""], leave_after=1), declared=23)
    assert ex.status is None  # nobody to answer
    assert counted(app, 499) == 1 and counted(app, 500) == 0


def test_bounded_shape(edge_app: FastAPI) -> None:
    deep = b'{"u_px": 1, "v_px": 2, "x": ' + b"[" * (MAX_DEPTH + 5) + b"]" * (MAX_DEPTH + 5) + b"}"
    ex = call(edge_app, "POST", "/map", auth("viewer"), Exchange([deep]))
    assert ex.status == 422 and "nested more than" in json.loads(ex.body)["error"]["message"]
    many = b'{"u_px": 1, "v_px": 2, "x": [' + b"0," * MAX_VALUES + b"0]}"
    ex = call(edge_app, "POST", "/map", auth("viewer"), Exchange([many]))
    assert ex.status == 422 and f"limit is {MAX_VALUES}" in json.loads(ex.body)["error"]["message"]


# -- numbers: type and range, everywhere a request carries them -----------------------------------------

@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, dict[str, Any]]]:
    app = make_app(tmp_path_factory.mktemp("edge"))
    with TestClient(app) as c:
        yield c, taught_model()


def taught_model() -> dict[str, Any]:
    """A shape model taught from a drawn part (what ``POST /pick/teach`` answers), as JSON."""
    img = np.zeros((480, 640), np.uint8)
    img[100:300, 200:400] = 200
    img[150:200, 250:300] = 40
    out: dict[str, Any] = json.loads(json.dumps(teach(img, (180, 80, 240, 240)).to_dict()))
    return out


DIGITS_400 = "1" * 400
FLOAT_400 = "1" + "0" * 398 + ".5"  # a float written out in 400 digits (1e398: an infinity as a double)
POSE = {"x_m": 0.4, "y_m": 0.0, "z_m": 0.3, "rx_rad": 3.14159, "ry_rad": 0.0, "rz_rad": 0.0}


def post_raw(c: TestClient, path: str, text: str, role: str = "engineer") -> Any:
    return c.post(path, content=text.encode(), headers={**auth(role), "Content-Type": "application/json"})


def refused(r: Any, field: str) -> str:
    assert r.status_code == 422, (r.status_code, r.text[:300])
    message: str = r.json()["error"]["message"]
    assert field in message, (field, message)
    return message


@pytest.mark.parametrize("key", list(POSE))
@pytest.mark.parametrize("value", [True, "0.4", None], ids=["bool", "string", "null"])
def test_motion_fields_take_json_numbers_only(client: tuple[TestClient, dict[str, Any]], key: str,
                                              value: Any) -> None:
    c, _ = client
    before = c.get("/robots/robot0/state", headers=auth("viewer")).json()["pose_ur"]
    r = c.post("/robots/robot0/move", json={"pose_ur": {**POSE, key: value}}, headers=auth("engineer"))
    refused(r, f"body.pose_ur.{key}")
    assert c.get("/robots/robot0/state", headers=auth("viewer")).json()["pose_ur"] == pytest.approx(before, abs=1e-9)


@pytest.mark.parametrize("literal", [DIGITS_400, FLOAT_400, "-" + DIGITS_400, "0." + "0" * 398 + "1"],
                         ids=["400-digit int", "400-digit float", "negative", "400-digit fraction"])
def test_400_digit_numbers_in_motion_are_refused_naming_the_field(client: tuple[TestClient, dict[str, Any]],
                                                                  literal: str) -> None:
    c, _ = client
    text = json.dumps({"pose_ur": {**POSE, "z_m": "@"}, "speed_m_s": 0.05}).replace('"@"', literal)
    msg = refused(post_raw(c, "/robots/robot0/move", text), "body.pose_ur.z_m")
    assert f"at most {MAX_NUMBER_CHARS}" in msg
    text = json.dumps({"T_base_tool": [[1, 0, 0, "@"], [0, -1, 0, 0], [0, 0, -1, 0.3], [0, 0, 0, 1]]})
    refused(post_raw(c, "/robots/robot0/move", text.replace('"@"', literal)), "body.T_base_tool.0.3")


MODEL_PLACES = [  # (where in the part model, the field named)
    (("teach", "reference_px", 0), "teach.reference_px.0"),
    (("teach", "roi", 2), "teach.roi.2"),
    (("teach", "image_size", 1), "teach.image_size.1"),
    (("teach", "params", "min_contrast"), "teach.params.min_contrast"),
    (("shape", "levels", 0, "points", 3, 1), "shape.levels.0.points.3.1"),
    (("shape", "levels", 0, "features", 0), "shape.levels.0.features.0"),
    (("format_version",), "format_version"),
]


def _set(doc: Any, place: tuple[Any, ...], value: Any) -> None:
    for k in place[:-1]:
        doc = doc[k]
    doc[place[-1]] = value


def _recipes(c: TestClient) -> Any:
    return c.get("/recipes", headers=auth("viewer")).json()


@pytest.mark.parametrize(("place", "field"), MODEL_PLACES, ids=[f for _, f in MODEL_PLACES])
def test_numbers_in_a_recipes_models_are_checked(client: tuple[TestClient, dict[str, Any]],
                                                 place: tuple[Any, ...], field: str) -> None:
    c, model = client
    before = _recipes(c)
    for bad in (DIGITS_400, FLOAT_400, "true", '"7"', "1e300", "-12345678901234567890"):
        m = json.loads(json.dumps(model))
        _set(m, place, "@")
        text = json.dumps({"recipe_id": 60, "recipe": {"name": "hostile", "models": [m]}}).replace('"@"', bad)
        refused(post_raw(c, "/recipes", text), f"body.recipe.models.0.{field}")
    assert _recipes(c) == before  # nothing stored
    assert c.get("/recipes/60", headers=auth("viewer")).status_code == 404


@pytest.mark.parametrize(("key", "value"), [("grasp_z_mm", True), ("grasp_z_mm", "5"), ("speed_m_s", True),
                                            ("search.max_count", 5.0), ("search.max_count", True),
                                            ("search.mirrored", 1), ("tool_rotvec_rad", [3.14, "0", 0]),
                                            ("plane_z_mm", 10**400)])
def test_recipe_fields_are_strict(client: tuple[TestClient, dict[str, Any]], key: str, value: Any) -> None:
    c, model = client
    recipe: dict[str, Any] = {"name": "strict", "models": [model]}
    if key.startswith("search."):
        recipe["search"] = {key.removeprefix("search."): value}
    else:
        recipe[key] = value
    r = c.post("/recipes", json={"recipe_id": 61, "recipe": recipe}, headers=auth("engineer"))
    refused(r, f"body.recipe.{key}")
    assert c.get("/recipes/61", headers=auth("viewer")).status_code == 404


def test_a_taught_model_round_trips_and_a_large_recipe_is_stored(client: tuple[TestClient, dict[str, Any]]) -> None:
    c, model = client
    big = json.loads(json.dumps(model))
    pts = big["shape"]["levels"][0]["points"]
    while len(json.dumps(big)) < 200_000:  # over OFF_LOOP_BYTES: parsed and validated in the body pool
        pts.extend(pts[:500])
    r = c.post("/recipes", json={"recipe_id": 62, "recipe": {"name": "large", "models": [model, big],
                                                             "plane_z_mm": 0}}, headers=auth("engineer"))
    assert r.status_code == 201, r.text[:300]
    stored = c.get("/recipes/62", headers=auth("viewer")).json()["data"]["models"]
    assert stored == [model, big]  # stored as taught: no keys added or dropped
    big["shape"]["levels"][0]["points"][-1][1] = True
    r = c.post("/recipes", json={"recipe_id": 63, "recipe": {"name": "large", "models": [big]}},
               headers=auth("engineer"))
    refused(r, f"body.recipe.models.0.shape.levels.0.points.{len(pts) - 1}.1")


def test_other_routes_take_json_numbers_only(client: tuple[TestClient, dict[str, Any]]) -> None:
    c, _ = client
    refused(c.post("/map", json={"u_px": True, "v_px": 1}, headers=auth("viewer")), "body.u_px")
    refused(c.post("/map", json={"u_px": 1, "v_px": "2"}, headers=auth("viewer")), "body.v_px")
    refused(c.post("/map", json={"u_px": 1, "v_px": 2, "robot_pose_ur": [0.4, 0, 0.5, True, 0, 0]},
                   headers=auth("viewer")), "body.robot_pose_ur.3")
    refused(c.post("/pick", json={"recipe_id": True}, headers=auth("operator")), "body.recipe_id")
    refused(c.post("/pick", json={"recipe_id": 1, "move": "yes"}, headers=auth("engineer")), "body.move")
    refused(c.post("/pick/teach", json={"roi": [10, 10, "20", 20]}, headers=auth("engineer")), "body.roi.2")
    refused(c.post("/calibrations/1/activate", json={"force": 1}, headers=auth("engineer")), "body.force")
    r = post_raw(c, "/routines/verify", '{"tolerance_px": true}', "operator")
    assert r.status_code == 422 and "tolerance_px" in r.text, r.text


# -- the safety routes have threads of their own --------------------------------------------------------

def test_safety_routes_answer_while_every_default_worker_thread_is_busy(
        client: tuple[TestClient, dict[str, Any]]) -> None:
    """A flood that holds all of anyio's default worker threads (what sync routes and
    run_in_threadpool use) must not delay Stop, resume, state, motion or /health."""
    c, _ = client
    assert c.portal is not None
    hold_s = 4.0
    tokens = c.portal.call(lambda: anyio.to_thread.current_default_thread_limiter().total_tokens)
    busy = [c.portal.start_task_soon(anyio.to_thread.run_sync, time.sleep, hold_s) for _ in range(int(tokens) + 5)]
    try:
        wait_until(lambda: c.portal.call(  # type: ignore[union-attr]
            lambda: anyio.to_thread.current_default_thread_limiter().borrowed_tokens) >= tokens,
            hold_s / 2, "every default worker thread held")
        t0 = time.perf_counter()
        for method, path, role in (("POST", "/robots/robot0/stop", "operator"),
                                   ("GET", "/robots/robot0/state", "viewer"),
                                   ("GET", "/robots/robot0/motion", "viewer"),
                                   ("POST", "/robots/robot0/resume", "engineer")):
            r = c.request(method, path, headers=auth(role))
            assert r.status_code == 200, (path, r.text)
        assert c.get("/health").status_code == 200
        elapsed_s = time.perf_counter() - t0
        assert elapsed_s < 0.5 * hold_s, elapsed_s  # answered while the default pool was still full
    finally:
        for f in busy:
            f.result(30)
