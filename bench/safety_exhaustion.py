"""Exhaustion rows of the safety bench (issue 34): Stop while thousands of connections are held open.

A ``cellctl serve`` of the virtual cell with the Modbus server on; a flood process (nice 19, its
own open-files limit raised, one plain loop over non-blocking sockets) holds ``http`` slow-header
HTTP connections — each sends half a request line and then nothing, from 20 loopback source
addresses (127.0.0.2-21), and opens a new one 1 s after the server closes it, as a patient
attacker would — and ``modbus`` idle Modbus TCP connections (connect, send nothing, reconnect 1 s
after the server closes one). While it holds them (after a ramp-up), a fresh client times
``POST /robots/robot0/stop`` (operator) and ``GET /health`` on new connections, then resumes; the
service's log growth and its open descriptors (sampled) are reported, with an idle baseline of
the same calls in the same run (the machine is shared).

Rows: the service at the unit's ``LimitNOFILE`` (65,536, or this machine's hard limit) with both
floods, and at the 1,024 descriptors the unit had before (HTTP flood alone, started under
``prlimit``): the HTTP cap then falls to 512 and the reserve keeps Stop reachable.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import yaml

from cellctl.cli import main as cellctl_main
from cellctl.config import default_config_text

CELLCTL = str(Path(sys.executable).with_name("cellctl"))
TARGET_S = 0.3
LOG_TARGET_BYTES = 1_000_000

FLOOD = r"""
import json, resource, socket, sys, time
http_port, modbus_port, n_http, n_modbus, hold_s = (int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]),
                                                    int(sys.argv[4]), float(sys.argv[5]))
soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
stats = {"http_opened": 0, "http_closed_by_server": 0, "modbus_opened": 0, "modbus_closed_by_server": 0,
         "connect_failed": 0, "peak_open": {"http": 0, "modbus": 0}}
slots = [("http", http_port, f"127.0.0.{2 + i % 20}") for i in range(n_http)]
slots += [("modbus", modbus_port, "127.0.0.1") for _ in range(n_modbus)]
conns = [None] * len(slots)      # an open socket, or None
retry_at = [0.0] * len(slots)    # when a closed slot may connect again (1 s after it was closed)

def connect(i):
    kind, port, source = slots[i]
    s = socket.socket()
    s.settimeout(2.0)
    try:
        s.bind((source, 0))
        s.connect(("127.0.0.1", port))
        if kind == "http":
            s.sendall(b"GET /health HTT")  # half a request line, then nothing
        s.setblocking(False)
    except OSError:
        s.close()
        stats["connect_failed"] += 1
        retry_at[i] = time.monotonic() + 1.0
        return
    conns[i] = s
    stats[kind + "_opened"] += 1

end = time.monotonic() + hold_s
while time.monotonic() < end:
    now = time.monotonic()
    for i, s in enumerate(conns):
        if s is None:
            if now >= retry_at[i] and time.monotonic() < end:
                connect(i)
            continue
        try:
            closed = s.recv(1) == b""
        except BlockingIOError:
            closed = False
        except OSError:
            closed = True
        if closed:
            s.close()
            conns[i] = None
            stats[slots[i][0] + "_closed_by_server"] += 1
            retry_at[i] = now + 1.0
    for kind in ("http", "modbus"):
        n = sum(1 for i, s in enumerate(conns) if s is not None and slots[i][0] == kind)
        stats["peak_open"][kind] = max(stats["peak_open"][kind], n)
    time.sleep(0.2)
print(json.dumps(stats))
"""


@dataclass
class Exhaustion:
    name: str
    stop_ms: list[float] = field(default_factory=list)
    health_ms: list[float] = field(default_factory=list)
    connect_ms: list[float] = field(default_factory=list)
    idle_stop_ms: list[float] = field(default_factory=list)
    idle_health_ms: list[float] = field(default_factory=list)
    load: tuple[float, float] = (0.0, 0.0)
    failures: list[str] = field(default_factory=list)
    log_bytes: int = 0
    fds_max: int = 0
    flood: dict[str, Any] = field(default_factory=dict)
    note: str = ""


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(tmp: Path, nofile: int | None) -> tuple[subprocess.Popen[bytes], str, int, dict[str, str], Path]:
    cfg = tmp / "cell.yaml"
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    modbus_port = _free_port()
    data["plc"] = {"modbus": {"enabled": True, "host": "127.0.0.1", "port": modbus_port}}
    cfg.write_text(yaml.safe_dump(data))
    tokens = {}
    for role in ("operator", "engineer"):
        out = tmp / f"{role}.json"
        with contextlib.redirect_stdout(io.StringIO()):
            if cellctl_main(["token", "add", "--config", str(cfg), "--name", role, "--role", role, "--out", str(out)]):
                raise RuntimeError("cellctl token add failed")
        tokens[role] = json.loads(out.read_text())["token"]
    port = _free_port()
    cmd = [CELLCTL, "serve", "--config", str(cfg), "--port", str(port), "--log-format", "json"]
    if nofile is not None:
        cmd = [shutil.which("prlimit") or "prlimit", f"--nofile={nofile}:{nofile}", "--", *cmd]
    log = tmp / "serve.log"
    proc = subprocess.Popen(cmd, env={**os.environ, "CELLCTL_DATA_DIR": str(tmp / "data")},
                            stdout=subprocess.DEVNULL, stderr=log.open("wb"))
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            h = httpx.get(base + "/health", timeout=2)
            if h.status_code == 200 and h.json().get("status") != "starting":
                return proc, base, modbus_port, tokens, log
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    proc.kill()
    raise RuntimeError(f"cellctl serve did not start: {log.read_text()[-2000:]}")


def _fds(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return 0


def _timed(fn: object) -> tuple[float, str | None]:
    """(ms, problem) of one request (problem: None when it answered 200)."""
    t0 = time.perf_counter()
    try:
        r = fn()  # type: ignore[operator]
        problem = None if r.status_code == 200 else f"HTTP {r.status_code}"
    except httpx.HTTPError as exc:
        problem = type(exc).__name__
    return (time.perf_counter() - t0) * 1e3, problem


def _round(base: str, port: int, op: dict[str, str], eng: dict[str, str]
           ) -> tuple[tuple[float, str | None], tuple[float, str | None], float]:
    """One Stop and one /health, each on a new connection, then a resume; and a bare TCP connect's time (ms)."""
    import socket

    t0 = time.perf_counter()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=30):
            connect_ms = (time.perf_counter() - t0) * 1e3
    except OSError:
        connect_ms = float("nan")
    stop = _timed(lambda: httpx.post(base + "/robots/robot0/stop", headers=op, timeout=30))
    health = _timed(lambda: httpx.get(base + "/health", timeout=30))
    with contextlib.suppress(httpx.HTTPError):
        httpx.post(base + "/robots/robot0/resume", headers=eng, timeout=30)
    return stop, health, connect_ms


def run_one(name: str, n_http: int, n_modbus: int, tries: int, nofile: int | None, ramp_s: float = 12.0,
            every_s: float = 2.0) -> Exhaustion:
    row = Exhaustion(name)
    with tempfile.TemporaryDirectory(prefix="cellctl-exhaustion-") as d:
        tmp = Path(d)
        proc, base, modbus_port, tokens, log = _serve(tmp, nofile)
        port = int(base.rsplit(":", 1)[1])
        try:
            op = {"Authorization": f"Bearer {tokens['operator']}"}
            eng = {"Authorization": f"Bearer {tokens['engineer']}"}
            row.load = (os.getloadavg()[0], 0.0)
            for _ in range(tries):  # the idle baseline, in the same run: the machine is shared
                stop, health, _ = _round(base, port, op, eng)
                row.idle_stop_ms.append(stop[0])
                row.idle_health_ms.append(health[0])
                time.sleep(0.5)
            log_before = log.stat().st_size
            hold_s = ramp_s + tries * every_s + 3.0
            flood = subprocess.Popen(["nice", "-n", "19", sys.executable, "-c", FLOOD, str(port), str(modbus_port),
                                      str(n_http), str(n_modbus), str(hold_s)], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE)
            t_end = time.monotonic() + ramp_s
            while time.monotonic() < t_end:
                row.fds_max = max(row.fds_max, _fds(proc.pid))
                time.sleep(0.5)
            for _ in range(tries):
                stop, health, connect_ms = _round(base, port, op, eng)
                row.stop_ms.append(stop[0])
                row.health_ms.append(health[0])
                row.connect_ms.append(connect_ms)
                row.failures += [f"stop: {stop[1]}"] if stop[1] else []
                row.failures += [f"health: {health[1]}"] if health[1] else []
                row.fds_max = max(row.fds_max, _fds(proc.pid))
                time.sleep(every_s)
            row.load = (row.load[0], os.getloadavg()[0])
            out, err = flood.communicate(timeout=hold_s + 60)
            row.flood = json.loads(out.decode().strip().splitlines()[-1]) if out.strip() else {"error": err[-300:]}
            row.log_bytes = log.stat().st_size - log_before
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
    return row


def measure(tries: int) -> list[Exhaustion]:
    return [run_one("5,000 slow-header HTTP + 2,000 idle Modbus connections, service at its LimitNOFILE "
                    "(65,536 or the hard limit)", 5000, 2000, tries, None),
            run_one("5,000 slow-header HTTP connections, service at 1,024 descriptors (the unit's old default)",
                    5000, 0, tries, 1024)]


def table(rows: list[Exhaustion]) -> list[str]:
    lines = ["| load | Stop tries | Stop median / max ms | all Stops within 0.3 s | idle Stop median ms | "
             "/health median / max ms (idle median) | TCP connect median ms | failures | log growth | "
             "service's descriptors, max | load average start / end | what the flood got |", "|" + " --- |" * 12]
    for r in rows:
        f = r.flood
        peak: dict[str, Any] = f.get("peak_open") or {}
        got = (f"HTTP: {f.get('http_opened', 0)} opened, {f.get('http_closed_by_server', 0)} closed by the service, "
               f"peak {peak.get('http', 0)} open; Modbus: {f.get('modbus_opened', 0)} opened, "
               f"{f.get('modbus_closed_by_server', 0)} closed, peak {peak.get('modbus', 0)} open; "
               f"{f.get('connect_failed', 0)} connects failed")
        within = all(ms <= TARGET_S * 1e3 for ms in r.stop_ms) and not r.failures
        lines.append(
            f"| {r.name} | {len(r.stop_ms)} | {statistics.median(r.stop_ms):.1f} / {max(r.stop_ms):.1f} | "
            f"{'yes' if within else 'no'} | {statistics.median(r.idle_stop_ms):.1f} | "
            f"{statistics.median(r.health_ms):.1f} / {max(r.health_ms):.1f} "
            f"({statistics.median(r.idle_health_ms):.1f}) | {statistics.median(r.connect_ms):.1f} | "
            f"{len(r.failures)}{': ' + ', '.join(sorted(set(r.failures))) if r.failures else ''} | "
            f"{r.log_bytes / 1e3:.1f} kB ({'within' if r.log_bytes <= LOG_TARGET_BYTES else 'over'} 1 MB) | "
            f"{r.fds_max} | {r.load[0]:.1f} / {r.load[1]:.1f} | {got} |")
    return lines


HEADING = "## Stop while connections are held (issue 34)"


def section(rows: list[Exhaustion], command: str) -> str:
    """The results file's section for these rows."""
    return "\n".join([
        HEADING, "",
        f"`{command}`. The flood holds its connections open from a process of its own (nice 19); after "
        "a 12 s ramp-up a fresh client times Stop (operator) and /health on new connections every 2 s, resuming "
        f"after each Stop. Targets: Stop within {TARGET_S} s, the log grows at most 1 MB.", "",
        *table(rows), "",
        "Before (issue 34's report): 1,100 slow-header connections (or 1,100 idle Modbus ones) made Stop "
        "unreachable (9 fresh Stops over 27 s all timed out) and the log grew 53-94 MB in 15-20 s. Now a "
        "connection's headers must arrive within http.header_timeout_s (10 s); over http.max_connections_per_address"
        " (256) or the total cap (http.max_connections, 4,096, lowered to keep 512 descriptors in reserve) the "
        "oldest idle connection is closed to admit the new one; repeated log messages are counted and summarised. "
        "The idle Modbus connections are the PLC server's to close (its row measures what that server does).", "",
        "Read the Stop columns against the idle one: on this shared 2-core machine (load average in the row) "
        "an idle Stop — its halt, then its latch and audit rows written to SQLite with fsync — takes what the "
        "other work leaves it, and the flood's cost is the difference. The service's descriptors show the reserve: "
        "at 1,024 the process stays below its limit (uvicorn's 2,048 backlog had it accept past the limit, pause "
        "accept() for a second and answer Stop in 1.3 s).", ""])


def splice(text: str, new_section: str) -> str:
    """``text`` (a results file) with its exhaustion section replaced by ``new_section`` (or inserted before
    its notes)."""
    if HEADING in text:
        head, _, rest = text.partition(HEADING)
        nxt = rest.find("\n## ")
        return head + new_section + ("\n" + rest[nxt + 1:] if nxt >= 0 else "")
    if "\n## Notes" in text:
        head, _, rest = text.partition("\n## Notes")
        return head + "\n" + new_section + "\n## Notes" + rest
    return text.rstrip("\n") + "\n\n" + new_section
