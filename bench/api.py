"""REST latency under load: cellctl's routes against a bare uvicorn "hello" endpoint, same run.

Starts ``cellctl serve`` (virtual cell) and a bare uvicorn app on loopback, then drives each with
``--clients`` concurrent asyncio clients for ``--seconds``: ``GET /robots/robot0/state``,
``POST /map`` (active N-point calibration made by the jog-to-mark routine first) and, with fewer
clients, ``GET /cameras/cam0/image`` (each frame is a ~0.5 s render). Prints a markdown table of
p50/p99 latency and errors and the ratio to the bare endpoint's p99, and saves it to
``bench/results/api.md``. Target (issue 7): p99 of state and map within 3x of the bare endpoint.

    .venv/bin/python bench/api.py [--clients 50] [--seconds 30]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

HELLO_APP = """
from fastapi import FastAPI
app = FastAPI()

@app.get("/hello")
def hello() -> dict:
    return {"hello": "world"}
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_up(url: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(url, timeout=2).status_code < 500:
                return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise RuntimeError(f"{url} did not come up")


async def load(url: str, method: str, body: dict[str, object] | None, headers: dict[str, str], clients: int,
               seconds: float) -> tuple[list[float], int, int]:
    latencies: list[float] = []
    errors = 0
    end = time.monotonic() + seconds
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(headers=headers, timeout=30.0, limits=limits) as http:

        async def worker() -> None:
            nonlocal errors
            while time.monotonic() < end:
                t0 = time.perf_counter()
                try:
                    r = await http.request(method, url, json=body)
                    ok = r.status_code < 400
                except httpx.HTTPError:
                    ok = False
                latencies.append(time.perf_counter() - t0)
                if not ok:
                    errors += 1

        await asyncio.gather(*(worker() for _ in range(clients)))
    return latencies, errors, len(latencies)


def row(name: str, lat: list[float], errors: int, n: int, ref_p99: float | None, clients: int
        ) -> tuple[str, float]:
    a = np.array(lat) * 1e3
    p50, p99 = np.percentile(a, 50), np.percentile(a, 99)
    ratio = f"{p99 / ref_p99:.2f}x" if ref_p99 else "1 (reference)"
    return f"| {name} | {clients} | {n} | {p50:.1f} | {p99:.1f} | {ratio} | {errors} |", float(p99)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=30.0)
    args = ap.parse_args()
    from tests.support.served import start_served, stop_served

    tmp = Path(tempfile.mkdtemp(prefix="bench-api-"))
    (tmp / "hello_app.py").write_text(HELLO_APP)
    hello_port = free_port()
    hello = subprocess.Popen([sys.executable, "-m", "uvicorn", "hello_app:app", "--host", "127.0.0.1", "--port",
                              str(hello_port), "--log-level", "warning"], cwd=tmp)
    served = start_served(tmp)
    try:
        wait_up(f"http://127.0.0.1:{hello_port}/hello")
        headers = {"Authorization": f"Bearer {served.token}"}
        # An active N-point calibration for /map, made by the jog-to-mark routine with recorded points.
        with served.client(timeout_s=60) as http:
            job = http.post("/routines/jog-to-mark", json={"marks": 9}).json()["id"]
            for k in range(9):
                while http.get(f"/jobs/{job}").json()["waiting_for"] is None:
                    time.sleep(0.05)
                w = http.get(f"/jobs/{job}").json()["waiting_for"]
                http.post(f"/jobs/{job}/record", json={"x_mm": 300 + w["u_px"] * 0.4, "y_mm": 100 - w["v_px"] * 0.4
                                                       + 0.01 * k})
            while (j := http.get(f"/jobs/{job}").json())["state"] == "running":
                time.sleep(0.1)
            http.post(f"/calibrations/{j['result']['calibration_id']}/activate")
        base = served.base_url
        lines = ["| endpoint | clients | requests | p50 ms | p99 ms | p99 / bare p99 | errors |",
                 "| --- | --- | --- | --- | --- | --- | --- |"]
        lat, err, n = asyncio.run(load(f"http://127.0.0.1:{hello_port}/hello", "GET", None, {}, args.clients,
                                       args.seconds))
        line, ref = row("bare uvicorn GET /hello", lat, err, n, None, args.clients)
        lines.append(line)
        cases: tuple[tuple[str, str, str, dict[str, object] | None, int], ...] = (
            ("GET /robots/robot0/state", "GET", "/robots/robot0/state", None, args.clients),
            ("POST /map (n-point)", "POST", "/map", {"u_px": 640.0, "v_px": 480.0, "calibration": "npoint"},
             args.clients),
            ("GET /cameras/cam0/image", "GET", "/cameras/cam0/image", None, 4),
        )
        for name, method, path, body, clients in cases:
            lat, err, n = asyncio.run(load(base + path, method, body, headers, clients, args.seconds))
            line, _ = row(name, lat, err, n, ref, clients)
            lines.append(line)
        table = "\n".join(lines)
        header = (f"# REST latency under load ({args.clients} clients, {args.seconds:.0f} s each, one machine, "
                  f"{os.cpu_count()} cores)\n\nCommand: `.venv/bin/python bench/api.py --clients {args.clients} "
                  f"--seconds {args.seconds:.0f}`. Reference: a bare uvicorn+FastAPI endpoint in the same run. "
                  "Target: p99 of state and map within 3x of the bare endpoint's p99, no errors. The image "
                  "route grabs a new 1280x960 frame per request (the virtual camera adds fresh noise and "
                  "encodes a PNG each time), so it runs with 4 clients and has no target. The load generator "
                  "shares the 2 cores with the servers, so absolute times are the machine's; the ratios are the "
                  "result.\n\n")
        text = header + table + "\n"
        print(text)
        (REPO / "bench" / "results").mkdir(exist_ok=True)
        (REPO / "bench" / "results" / "api.md").write_text(text)
    finally:
        stop_served(served)
        hello.terminate()
        hello.wait()


if __name__ == "__main__":
    main()
