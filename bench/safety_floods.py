"""Stop, resume, state and /health latency while hostile clients flood the service (issue 21, item 3).

Used by ``bench/safety.py`` (the rows of ``bench/results/safety.md``). For each load, ``tries``
rounds of: ``POST /robots/robot0/stop`` (operator), ``POST /robots/robot0/resume`` (engineer),
``GET /robots/robot0/state`` (viewer), ``GET /health``, each timed from this process alone (it does
nothing else meanwhile); the floods run in a process of their own, so their clients never hold
this interpreter. Loads:

- **idle**: nothing else (the baseline, measured before the floods);
- **no-token 1e300 flood**: five clients without a token post ~7.8 MB bodies of ``1e300`` to the
  Stop route, ten bodies a round, round after round while the tries run (issue 21: Stop 1.5-8.9 s);
- **slow-body flood**: fifty connections with a viewer's token send ``POST /map`` headers and then
  one byte of the body every 0.5 s; each one refused (408 after ``http.body_timeout_s``) is
  replaced at once, so fifty are open throughout (issue 21: never timed out, each drop a 500).

Loopback only; bounded in count (the tries) and time (a flood ends with the tries, at most 120 s).
Run alone: ``.venv/bin/python bench/safety_floods.py`` (serves its own virtual cell).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

ROUTES = ("stop", "resume", "state", "health")
TARGET_MS = 100.0
BODY = b"[" + b"1e300," * 1_300_000 + b"1]"  # ~7.8 MB
MAX_FLOOD_S = 120.0


@dataclass
class StopLoad:
    """The latencies (ms) of each safety route under one load, and what the flood sent."""

    name: str
    ms: dict[str, list[float]] = field(default_factory=lambda: {r: [] for r in ROUTES})
    note: str = "—"


def time_safety_routes(base: str, tokens: dict[str, str], tries: int, gap_s: float = 0.05
                       ) -> dict[str, list[float]]:
    """``tries`` rounds of stop, resume, state and /health, ``gap_s`` apart; each answer must be 200."""
    out: dict[str, list[float]] = {r: [] for r in ROUTES}
    calls = {"stop": ("POST", "/robots/robot0/stop", "operator"),
             "resume": ("POST", "/robots/robot0/resume", "engineer"),
             "state": ("GET", "/robots/robot0/state", "viewer"), "health": ("GET", "/health", None)}
    with httpx.Client(base_url=base, timeout=60.0) as http:
        for _ in range(tries):
            for route in ROUTES:
                method, path, role = calls[route]
                headers = {"Authorization": f"Bearer {tokens[role]}"} if role else {}
                t0 = time.perf_counter()
                r = http.request(method, path, headers=headers)
                out[route].append((time.perf_counter() - t0) * 1e3)
                if r.status_code != 200:
                    raise RuntimeError(f"{method} {path} answered {r.status_code}: {r.text[:200]}")
            time.sleep(gap_s)
    return out


def cpu_s(pid: int) -> float:
    """User + system CPU seconds the process has used (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(base: str, tokens: dict[str, str], tries: int, server_pid: int) -> list[StopLoad]:
    """The three loads, in order: idle, the no-token flood, the slow-body flood."""
    idle = StopLoad("idle (baseline)")
    idle.ms = time_safety_routes(base, tokens, tries)
    loads = [idle]
    for mode, name in (("no-token", "no-token flood: 5 clients x ~7.8 MB bodies of 1e300, 10 a round"),
                       ("slow-body", "slow-body flood: 50 connections trickling 1 byte / 0.5 s")):
        load = StopLoad(name)
        # The attacker runs at the lowest priority: across a network it would use its own machine's
        # CPU, not the cell's; on loopback it shares this machine's two cores with the service.
        flood = subprocess.Popen(["nice", "-n", "19", sys.executable, __file__, "flood", mode, base, tokens["viewer"]],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert flood.stdout is not None
            flood.stdout.readline()  # "started": the flood is running
            time.sleep(1.0)
            cpu0, t0 = cpu_s(server_pid), time.monotonic()
            # The slow-body rounds are spread over two body timeouts, so refusals and new connections fall in them.
            load.ms = time_safety_routes(base, tokens, tries, 0.05 if mode == "no-token" else 0.6)
            busy = (cpu_s(server_pid) - cpu0) / (time.monotonic() - t0)
        finally:
            out, _ = flood.communicate("stop\n", timeout=MAX_FLOOD_S)
        load.note = f"{json.loads(out.strip().splitlines()[-1])['note']}; the service used {busy:.0%} of a core"
        loads.append(load)
    return loads


def table(loads: list[StopLoad]) -> list[str]:
    """Markdown rows: one per load and route, the idle median beside each."""
    idle = {r: statistics.median(loads[0].ms[r]) for r in ROUTES}
    lines = ["| load | route | tries | median ms | p95 ms | max ms | idle median ms | all within "
             f"{TARGET_MS:.0f} ms | what the flood sent / got |", "|" + " --- |" * 9]
    for load in loads:
        for i, r in enumerate(ROUTES):
            ms = sorted(load.ms[r])
            p95 = ms[min(len(ms) - 1, round(0.95 * (len(ms) - 1)))]
            lines.append(f"| {load.name if i == 0 else ''} | {r} | {len(ms)} | {statistics.median(ms):.1f} | "
                         f"{p95:.1f} | {ms[-1]:.1f} | {idle[r]:.1f} | {'yes' if ms[-1] <= TARGET_MS else 'no'} | "
                         f"{load.note if i == 0 else ''} |")
    return lines


# -- the floods (run as their own process: `safety_floods.py flood MODE BASE VIEWER_TOKEN`) ----------------

def no_token_flood(base: str, stop: threading.Event) -> str:
    outcomes: list[str] = []

    def client() -> None:
        with httpx.Client(base_url=base, timeout=30.0) as http:
            while not stop.is_set():
                try:
                    r = http.post("/robots/robot0/stop", content=BODY, headers={"Content-Type": "application/json"})
                    outcomes.append(str(r.status_code))
                except httpx.HTTPError as exc:  # the server closed the connection instead of reading the body
                    outcomes.append(type(exc).__name__)

    _run(client, 5, stop)
    counts = {k: outcomes.count(k) for k in sorted(set(outcomes))}
    return f"{len(outcomes)} bodies ({len(outcomes) * len(BODY) / 1e6:.0f} MB): " + ", ".join(
        f"{k} x{v}" for k, v in counts.items())


def slow_body_flood(base: str, token: str, stop: threading.Event) -> str:
    host, port = base.removeprefix("http://").split(":")
    head = (b"POST /map HTTP/1.1\r\nHost: cell\r\nContent-Type: application/json\r\nAuthorization: Bearer "
            + token.encode() + b"\r\nContent-Length: 1000\r\n\r\n{")
    answers: list[bytes] = []
    opened = 0

    def connect() -> socket.socket:
        nonlocal opened
        s = socket.create_connection((host, int(port)), timeout=10)
        s.sendall(head)
        s.setblocking(False)
        opened += 1
        return s

    socks = [connect() for _ in range(50)]
    while not stop.is_set():
        for i, s in enumerate(socks):
            try:
                data = s.recv(65536)
            except BlockingIOError:
                with contextlib.suppress(OSError):  # answered and closed meanwhile: read next round
                    s.send(b" ")
                continue
            except OSError:
                data = b""
            answers.append(data)
            s.close()
            socks[i] = connect()  # keep fifty open
        stop.wait(0.5)
    for s in socks:
        s.close()
    n408 = sum(a.startswith(b"HTTP/1.1 408") for a in answers)
    return f"{opened} connections, {len(answers)} answered: {n408} x 408, {len(answers) - n408} other"


def _run(target: object, n: int, stop: threading.Event) -> None:
    threads = [threading.Thread(target=target, daemon=True) for _ in range(n)]  # type: ignore[arg-type]
    for t in threads:
        t.start()
    stop.wait(MAX_FLOOD_S)
    stop.set()
    for t in threads:
        t.join(60.0)


def flood_main(mode: str, base: str, token: str) -> None:
    stop = threading.Event()
    result: list[str] = []

    def run() -> None:
        result.append(no_token_flood(base, stop) if mode == "no-token" else slow_body_flood(base, token, stop))

    worker = threading.Thread(target=run)
    worker.start()
    print("started", flush=True)
    sys.stdin.readline()  # told to stop (or the bench is gone)
    stop.set()
    worker.join(MAX_FLOOD_S)
    print(json.dumps({"note": result[0] if result else "the flood did not finish"}), flush=True)


def main() -> int:
    import tempfile

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.safety import serve

    with tempfile.TemporaryDirectory(prefix="cellctl-stop-floods-") as d:
        proc, base, tokens = serve(Path(d))
        try:
            print("\n".join(table(measure(base, tokens, 20, proc.pid))))
        finally:
            proc.terminate()
            proc.wait(20)
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "flood":
        flood_main(sys.argv[2], sys.argv[3], sys.argv[4])
    else:
        sys.exit(main())
