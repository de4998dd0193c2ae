"""Floods against a served cell: huge bodies without a token, slow bodies, and event streams by the hundred.

A ``cellctl serve`` of the virtual cell with three tokens, small stream limits
(``http.max_event_streams: 6``, ``http.max_event_streams_per_token: 4``) and a short body timeout
(``http.body_timeout_s: 2``), called over loopback with httpx and raw sockets. Bounds are on
counts, on ``/health`` staying under 2 s and on Stop answering within a second while a flood
runs (the idle latency and the latencies under flood, against the 100 ms target, are in
``bench/results/safety.md``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import yaml

from cellctl.cli import main
from cellctl.config import default_config_text
from tests.conftest import Served, start_served, stop_served
from tests.support.wait import wait_until

MAX_STREAMS, MAX_STREAMS_PER_TOKEN = 6, 4
BODY_MB = 40
HEALTH_BOUND_S = 2.0
BODY_TIMEOUT_S = 2.0
STOP_BOUND_S = 1.0
"""Stop under a flood: seconds of delay would show; the 100 ms target is the bench's (bench/safety.py)."""


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("floods")
    data = yaml.safe_load(default_config_text())
    data["http"].update({"max_event_streams": MAX_STREAMS, "max_event_streams_per_token": MAX_STREAMS_PER_TOKEN,
                         "body_timeout_s": BODY_TIMEOUT_S})
    data["store"] = {"path": str(tmp / "cell.db")}
    cfg = tmp / "cell.yaml"
    cfg.write_text(yaml.safe_dump(data))
    tokens: dict[str, str] = {}
    for role in ("viewer", "operator", "engineer"):
        out = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-1", "--role", role,
                     "--out", str(out)]) == 0
        tokens[role] = json.loads(out.read_text())["token"]
    served = start_served(tmp, config=cfg, token=tokens["engineer"], timeout_s=120.0)
    try:
        yield served, tokens
    finally:
        stop_served(served)


class HealthProbe:
    """Calls ``/health`` every 20 ms from its own thread and keeps the latencies (s)."""

    def __init__(self, base_url: str) -> None:
        self.base_url = base_url
        self.latencies_s: list[float] = []
        self.failures: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        with httpx.Client(base_url=self.base_url, timeout=30.0) as http:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                try:
                    ok = http.get("/health").status_code == 200
                except httpx.HTTPError as exc:
                    ok = False
                    self.failures.append(repr(exc))
                self.latencies_s.append(time.perf_counter() - t0)
                if not ok:
                    self.failures.append("not 200")
                self._stop.wait(0.02)

    def __enter__(self) -> HealthProbe:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(35.0)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_an_oversized_body_is_refused_from_its_headers_alone(cell: tuple[Served, dict[str, str]]) -> None:
    served, _ = cell
    host, port = served.base_url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(b"POST /recipes HTTP/1.1\r\nHost: cell\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 40000000\r\n\r\n")  # and not one byte of the body
        answer = b""
        while b"\r\n\r\n" not in answer or not answer.rstrip().endswith(b"}"):
            chunk = s.recv(65536)
            if not chunk:
                break
            answer += chunk
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413"), head
    assert json.loads(body)["error"]["code"] == "body_too_large"
    assert b"8 MB" in body


def test_four_parallel_40_mb_bodies_without_a_token(cell: tuple[Served, dict[str, str]]) -> None:
    served, _ = cell
    rss_before = rss_mb(served.process.pid)
    results: list[tuple[str, int | str, float]] = []
    payload = b"x" * (BODY_MB * 1_000_000)

    def chunks() -> Iterator[bytes]:
        for _ in range(BODY_MB * 10):
            yield payload[:100_000]

    def post(kind: str) -> None:
        t0 = time.perf_counter()
        try:
            content = payload if kind == "declared" else chunks()  # chunked: no Content-Length
            r = httpx.post(served.base_url + "/recipes", content=content, timeout=60.0,
                           headers={"Content-Type": "application/json"})
            results.append((kind, r.status_code, time.perf_counter() - t0))
            # Declared too large: 413 from the headers; chunked (size unknown): 401 before a byte is read.
            assert r.json()["error"]["code"] == ("body_too_large" if kind == "declared" else "unauthorized")
        except (httpx.HTTPError, AssertionError) as exc:
            results.append((kind, repr(exc), time.perf_counter() - t0))

    with HealthProbe(served.base_url) as probe:
        wait_until(lambda: probe.latencies_s, 30.0, "a first /health answer")
        for kind in ("declared", "chunked"):
            threads = [threading.Thread(target=post, args=(kind,)) for _ in range(4)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(90.0)
        wait_until(lambda: len(probe.latencies_s) >= 5, 30.0, "five /health answers")
    assert [r[1] for r in results] == [413] * 4 + [401] * 4, results
    assert max(r[2] for r in results) < 30.0, results  # loose: the client writes 40 MB on a shared machine
    assert not probe.failures and len(probe.latencies_s) >= 5
    assert max(probe.latencies_s) < HEALTH_BOUND_S, (max(probe.latencies_s), statistics.median(probe.latencies_s))
    # Nothing of the bodies is kept: the server's memory does not grow by their size (4 x 40 MB).
    assert rss_mb(served.process.pid) - rss_before < 100.0


def test_a_body_under_the_limit_is_served(cell: tuple[Served, dict[str, str]]) -> None:
    served, tokens = cell
    big = {"recipe_id": 5, "recipe": {"name": "x" * 3_000_000, "models": [{}]}}  # 3 MB: under 8 MB
    r = httpx.post(served.base_url + "/recipes", json=big, timeout=60.0,
                   headers={"Authorization": f"Bearer {tokens['engineer']}"})
    assert r.status_code == 422 and "body.recipe.models.0.format_version" in r.json()["error"]["message"], r.text[:300]


def stop_and_resume(base_url: str, tokens: dict[str, str], tries: int) -> list[float]:
    """Stop (operator) then resume (engineer) ``tries`` times; the Stops' latencies (s). Each must answer 200."""
    latencies = []
    with httpx.Client(base_url=base_url, timeout=30.0) as http:
        for _ in range(tries):
            t0 = time.perf_counter()
            r = http.post("/robots/robot0/stop", headers={"Authorization": f"Bearer {tokens['operator']}"})
            latencies.append(time.perf_counter() - t0)
            assert r.status_code == 200 and r.json()["latched"], r.text
            r = http.post("/robots/robot0/resume", headers={"Authorization": f"Bearer {tokens['engineer']}"})
            assert r.status_code == 200, r.text
            time.sleep(0.05)
    return latencies


NO_TOKEN_FLOOD = """
import json, sys, threading, httpx
base, body, outcomes, stop = sys.argv[1], b"[" + b"1e300," * 1_300_000 + b"1]", [], threading.Event()
first = threading.Event()
def client():
    with httpx.Client(base_url=base, timeout=30.0) as http:
        while not stop.is_set():
            try:
                outcomes.append(http.post("/robots/robot0/stop", content=body,
                                          headers={"Content-Type": "application/json"}).status_code)
            except httpx.HTTPError as exc:  # the server closes the connection rather than read the body
                outcomes.append(type(exc).__name__)
            if len(outcomes) >= 10:
                first.set()
threads = [threading.Thread(target=client, daemon=True) for _ in range(5)]
for t in threads:
    t.start()
first.wait(120)
print("started", len(outcomes), flush=True)
sys.stdin.readline()
stop.set()
for t in threads:
    t.join(30)
print(json.dumps(outcomes), flush=True)
"""
"""Five clients without a token posting ~7.8 MB bodies of 1e300 until told to stop (run as its own
process at nice 19: its clients do not share this interpreter, or the machine's CPU first, with the
Stop being timed)."""


def test_stop_is_not_delayed_by_a_no_token_flood_of_large_numbers(cell: tuple[Served, dict[str, str]]) -> None:
    """Issue 21: 7.8 MB bodies of ``1e300`` without a token, five at a time, made Stop take 1.5-8.9 s.
    Now each is refused (401) from its headers, its body never read or parsed."""
    served, tokens = cell
    flood = subprocess.Popen(["nice", "-n", "19", sys.executable, "-c", NO_TOKEN_FLOOD, served.base_url],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert flood.stdout is not None
        word, before = flood.stdout.readline().split()
        assert word == "started"
        latencies = stop_and_resume(served.base_url, tokens, 10)
    finally:
        out, _ = flood.communicate("stop\n", timeout=60)
    outcomes = json.loads(out.strip().splitlines()[-1])
    # the flood was at full tilt (10 bodies refused) before the Stops were timed and went on during them
    assert len(outcomes) > int(before) >= 10, (before, len(outcomes))
    assert 500 not in outcomes and 200 not in outcomes, outcomes[:20]
    assert max(latencies) < STOP_BOUND_S, latencies


def read_to_close(s: socket.socket, timeout_s: float = 5.0) -> bytes:
    """The rest of an answer the server ends by closing the connection: its headers and body can come
    in separate segments, and a first read may hold only the headers."""
    s.settimeout(timeout_s)
    rest = b""
    with contextlib.suppress(OSError):
        while chunk := s.recv(65536):
            rest += chunk
    return rest


def trickle(base_url: str, token: str, n: int, start: threading.Event, answers: list[bytes]) -> None:
    """``n`` connections that send a body's first bytes, then one byte every 0.4 s; the answers, as they come."""
    host, port = base_url.removeprefix("http://").split(":")
    socks = []
    for _ in range(n):
        s = socket.create_connection((host, int(port)), timeout=30)
        s.sendall(b"POST /map HTTP/1.1\r\nHost: cell\r\nContent-Type: application/json\r\n"
                  b"Authorization: Bearer " + token.encode() + b"\r\nContent-Length: 1000\r\n\r\n{")
        socks.append(s)
    start.set()
    deadline = time.monotonic() + 30
    open_socks = list(socks)
    while open_socks and time.monotonic() < deadline:
        for s in list(open_socks):
            with contextlib.suppress(OSError):  # the server may have answered and closed
                s.sendall(b" ")
            s.settimeout(0.001)
            try:
                data = s.recv(65536)
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                data = b""
            answers.append(data + read_to_close(s) if data else data)
            open_socks.remove(s)
        time.sleep(0.4)
    for s in socks:
        s.close()


def test_slow_bodies_time_out_as_client_errors_and_stop_is_not_delayed(cell: tuple[Served, dict[str, str]]) -> None:
    """Issue 21: 50 clients trickling bodies stayed open for good and each drop counted as a 500."""
    served, tokens = cell
    with served.client(tokens["viewer"]) as http:
        before = http.get("/metrics").text
    start = threading.Event()
    answers: list[bytes] = []
    t0 = time.monotonic()
    trickler = threading.Thread(target=trickle, args=(served.base_url, tokens["viewer"], 50, start, answers))
    trickler.start()
    assert start.wait(30)
    latencies = stop_and_resume(served.base_url, tokens, 10)
    trickler.join(60)
    assert len(answers) == 50, len(answers)
    assert all(a.startswith(b"HTTP/1.1 408") and b"body_timeout" in a for a in answers), answers[:3]
    assert time.monotonic() - t0 < BODY_TIMEOUT_S + 20  # none is held much past the timeout
    assert max(latencies) < STOP_BOUND_S, latencies
    with served.client(tokens["viewer"]) as http:
        after = http.get("/metrics").text
    assert counted(after, "408") - counted(before, "408") == 50
    assert counted(after, "500") == counted(before, "500")


def test_a_client_that_leaves_mid_body_is_counted_as_a_client_error(cell: tuple[Served, dict[str, str]]) -> None:
    """Issue 21: each client that dropped its connection mid-body was logged and counted as a 500."""
    served, tokens = cell
    host, port = served.base_url.removeprefix("http://").split(":")
    with served.client(tokens["viewer"]) as http:
        before = http.get("/metrics").text
        for _ in range(5):
            with socket.create_connection((host, int(port)), timeout=10) as s:
                s.sendall(b"POST /map HTTP/1.1\r\nHost: cell\r\nContent-Type: application/json\r\n"
                          b"Authorization: Bearer " + tokens["viewer"].encode()
                          + b"\r\nContent-Length: 1000\r\n\r\n{\"u_px\": 1")  # and gone

        def counted_all() -> str | None:
            text = http.get("/metrics").text
            return text if counted(text, "499") - counted(before, "499") >= 5 else None

        after = wait_until(counted_all, 30.0, "five 499s counted")
    assert after is not None and counted(after, "500") == counted(before, "500")


def counted(metrics_text: str, status: str) -> float:
    """Requests counted with ``status`` in the latency histogram (any route)."""
    return sum(float(line.rsplit(" ", 1)[1]) for line in metrics_text.splitlines()
               if line.startswith("cellctl_http_request_duration_seconds_count{") and f'status="{status}"' in line)


class Streams:
    """Event streams opened at once by one token; the open ones (200) stay open until ``close``."""

    def __init__(self, base_url: str, token: str) -> None:
        self.client = httpx.AsyncClient(base_url=base_url, headers={"Authorization": f"Bearer {token}"},
                                        timeout=60.0, limits=httpx.Limits(max_connections=None,
                                                                          max_keepalive_connections=0))
        self.opened: list[httpx.Response] = []

    async def open(self, path: str, n: int) -> list[int]:
        async def one() -> httpx.Response:
            r = await self.client.send(self.client.build_request("GET", path), stream=True)
            if r.status_code != 200:
                await r.aread()
                await r.aclose()
            return r

        done = await asyncio.gather(*(one() for _ in range(n)))
        for r in done:
            if r.status_code == 429:
                assert json.loads(r.content)["error"]["code"] == "too_many_streams", r.content
        self.opened += [r for r in done if r.status_code == 200]
        return [r.status_code for r in done]

    async def close(self) -> None:
        for r in self.opened:
            await r.aclose()
        await self.client.aclose()


def test_150_event_streams_from_one_viewer(cell: tuple[Served, dict[str, str]]) -> None:
    served, tokens = cell
    with served.client(tokens["operator"]) as http:
        r = http.post("/routines/jog-to-mark", json={"step_timeout_s": 300})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        deadline = time.monotonic() + 60
        while http.get(f"/jobs/{job_id}").json()["state"] == "running" and \
                http.get(f"/jobs/{job_id}").json()["waiting_for"] is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert http.get(f"/jobs/{job_id}").json()["state"] == "running"  # waits for the operator: streams stay open
    path = f"/jobs/{job_id}/events"

    async def scenario() -> None:
        with HealthProbe(served.base_url) as probe:
            viewer, operator = Streams(served.base_url, tokens["viewer"]), Streams(served.base_url, tokens["operator"])
            viewer_status = await viewer.open(path, 150)
            assert viewer_status.count(200) == MAX_STREAMS_PER_TOKEN, viewer_status
            assert viewer_status.count(429) == 150 - MAX_STREAMS_PER_TOKEN
            # The same token spelled another way is the same token.
            respelled = Streams(served.base_url, tokens["viewer"])
            respelled.client.headers["Authorization"] = f"bearer   {tokens['viewer']}"
            assert await respelled.open(path, 2) == [429, 429]
            await respelled.close()
            # The cell-wide cap: another token gets what is left of MAX_STREAMS.
            op_status = await operator.open(path, 3)
            assert sorted(op_status) == [200] * (MAX_STREAMS - MAX_STREAMS_PER_TOKEN) + [429], op_status
            # The open streams are live: each has its first event.
            for r in viewer.opened[:1] + operator.opened[:1]:
                first = await asyncio.wait_for(r.aiter_text().__anext__(), 10.0)
                assert "event:" in first or "keep-alive" in first
            await asyncio.sleep(1.0)
            await viewer.close()
            await operator.close()
        assert not probe.failures
        assert max(probe.latencies_s) < HEALTH_BOUND_S, (max(probe.latencies_s), statistics.median(probe.latencies_s))
        # Closed streams give their slots back (the server notices within its 1 s event wait).
        deadline = time.monotonic() + 15
        while True:
            again = Streams(served.base_url, tokens["viewer"])
            status = await again.open(path, MAX_STREAMS_PER_TOKEN)
            await again.close()
            if status == [200] * MAX_STREAMS_PER_TOKEN or time.monotonic() > deadline:
                break
            await asyncio.sleep(1.0)
        assert status == [200] * MAX_STREAMS_PER_TOKEN, status

    try:
        asyncio.run(scenario())
    finally:
        with served.client(tokens["operator"]) as http:
            http.delete(f"/jobs/{job_id}")


def test_answers_that_are_not_streams_give_their_slot_back(cell: tuple[Served, dict[str, str]]) -> None:
    served, tokens = cell
    viewer = {"Authorization": f"Bearer {tokens['viewer']}"}
    with httpx.Client(base_url=served.base_url, timeout=20.0) as http:
        # Streams an earlier test closed hold their slots until the server notices (its 1 s event
        # wait): start once the viewer's slots are back, then every answer must return its own.
        deadline = time.monotonic() + 15
        while http.get("/jobs/nosuchjob/events", headers=viewer).status_code == 429 and time.monotonic() < deadline:
            time.sleep(0.5)
        for _ in range(3 * MAX_STREAMS):  # more than any limit: each slot must have come back
            r = http.get("/jobs/nosuchjob/events", headers=viewer)
            assert r.status_code == 404, r.text
            assert http.get("/jobs/nosuchjob/events").status_code == 401  # no token: refused, slot returned
