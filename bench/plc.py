"""PLC front-end benchmark (issue 9): Modbus TCP handshake and OPC UA method-call latency.

One ``cellctl serve`` of the virtual cell (true calibrations active, the bracket taught as recipe 1,
the way tests/plc prepares it) with both PLC servers on loopback. In the same run:

- **Modbus pick handshake** — a pymodbus client as the PLC writes COMMAND/RECIPE/SEQUENCE in one
  FC16 and polls 10..109 (one FC3, every 1 ms) until ECHO_SEQ is its sequence: PLC write ->
  result ready, as the PLC sees it. The server's own LATENCY register (request accepted -> answer
  posted) is read from the same snapshot.
- **Modbus idle handshake** — command 0 (answered at once): the protocol round trip alone.
- **OPC UA Pick** — an asyncua client calls ``Cell.Pick(1)``; the server-side time is
  ``LastPickLatencyMs``. **OPC UA read** — one status variable, the protocol round trip alone.
- **Peer: REST** ``POST /pick`` on the same served cell (httpx, the session token); server-side
  time is the answer's ``latency_ms.total``.

"overhead" = client-measured latency minus the server-side pick time of the same request: what the
front end adds. On the virtual cell the pick itself is dominated by the simulated camera rendering
a 1280x960 frame (seconds on a shared 2-core machine), so compare overheads, not totals.

Run: ``.venv/bin/python bench/plc.py [--n-modbus 200] [--n-opcua 50] [--n-rest 50] [--out bench/results/plc.md]``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from asyncua import Client, ua  # noqa: E402
from pymodbus.client import ModbusTcpClient  # noqa: E402

from cellctl.plc import modbus_server as mb  # noqa: E402
from cellctl.plc.opcua_server import NAMESPACE  # noqa: E402
from tests.conftest import stop_served  # noqa: E402
from tests.plc.conftest import RECIPE, PlcCell, start_plc_cell  # noqa: E402

POLL_S = 0.001


def pct(values: Sequence[float], q: float) -> float:
    s = sorted(values)
    if not s:
        return float("nan")
    k = min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))
    return s[k]


def row(name: str, client_ms: list[float], server_ms: list[float] | None) -> str:
    over = [c - s for c, s in zip(client_ms, server_ms, strict=True)] if server_ms else None
    cells = [name, str(len(client_ms)), f"{pct(client_ms, 50):.1f}", f"{pct(client_ms, 99):.1f}",
             f"{max(client_ms):.1f}"]
    cells += [f"{pct(server_ms, 50):.1f}" if server_ms else "-"]
    cells += [f"{pct(over, 50):.2f} / {pct(over, 99):.2f}" if over else "-"]
    return "| " + " | ".join(cells) + " |"


def bench_modbus(cell: PlcCell, n: int, command: int) -> tuple[list[float], list[float], int]:
    client = ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=10, retries=0)
    assert client.connect()
    seq = 1000 * (command + 1)
    client_ms: list[float] = []
    server_ms: list[float] = []
    failures = 0
    try:
        for _ in range(n):
            seq += 1
            t0 = time.perf_counter()
            client.write_registers(mb.COMMAND, [command, RECIPE, seq], device_id=1)
            while True:
                r = client.read_holding_registers(mb.STATUS, count=100, device_id=1).registers
                if r[mb.ECHO_SEQ - mb.STATUS] == seq:
                    break
                time.sleep(POLL_S)
            client_ms.append((time.perf_counter() - t0) * 1e3)
            server_ms.append(mb.words_int32(r[mb.LATENCY - mb.STATUS : mb.LATENCY - mb.STATUS + 2]) / 10)
            ok = r[0] & mb.DONE and (command != mb.CMD_PICK or r[mb.PICKS_REPORTED - mb.STATUS] >= 1)
            failures += 0 if ok else 1
    finally:
        client.close()
    return client_ms, server_ms, failures


async def bench_opcua(cell: PlcCell, n_pick: int, n_read: int) -> tuple[list[float], list[float], list[float]]:
    pick_ms: list[float] = []
    server_ms: list[float] = []
    read_ms: list[float] = []
    async with Client(cell.opcua_url, timeout=60, watchdog_intervall=60) as client:
        idx = await client.get_namespace_index(NAMESPACE)
        node = await client.nodes.objects.get_child(f"{idx}:Cell")
        pick = await node.get_child(f"{idx}:Pick")
        latency = await node.get_child(f"{idx}:LastPickLatencyMs")
        robot = await node.get_child(f"{idx}:RobotAvailable")
        for _ in range(n_pick):
            t0 = time.perf_counter()
            count, _, _ = await node.call_method(pick.nodeid, ua.Variant(RECIPE, ua.VariantType.Int32))
            pick_ms.append((time.perf_counter() - t0) * 1e3)
            assert count >= 1
            server_ms.append(float(await latency.read_value()))
        for _ in range(n_read):
            t0 = time.perf_counter()
            await robot.read_value()
            read_ms.append((time.perf_counter() - t0) * 1e3)
    return pick_ms, server_ms, read_ms


def bench_rest(cell: PlcCell, n: int) -> tuple[list[float], list[float]]:
    client_ms: list[float] = []
    server_ms: list[float] = []
    with cell.served.client(timeout_s=60) as http:
        for _ in range(n):
            t0 = time.perf_counter()
            r = http.post("/pick", json={"recipe_id": RECIPE})
            client_ms.append((time.perf_counter() - t0) * 1e3)
            r.raise_for_status()
            server_ms.append(float(r.json()["latency_ms"]["total"]))
    return client_ms, server_ms


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n-modbus", type=int, default=200, help="Modbus picks (and idle handshakes)")
    p.add_argument("--n-opcua", type=int, default=50, help="OPC UA Pick calls (reads: 4x as many)")
    p.add_argument("--n-rest", type=int, default=50, help="REST POST /pick calls (the peer)")
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "plc.md"))
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-plc-") as tmp:
        t_start = time.perf_counter()
        cell = start_plc_cell(Path(tmp))
        print(f"served cell ready in {time.perf_counter() - t_start:.1f} s", file=sys.stderr, flush=True)
        try:
            # One warm-up pick per front end (first-call costs are not the handshake).
            bench_modbus(cell, 1, mb.CMD_PICK)
            idle_c, idle_s, idle_fail = bench_modbus(cell, a.n_modbus, mb.CMD_IDLE)
            t0 = time.perf_counter()
            pick_c, pick_s, pick_fail = bench_modbus(cell, a.n_modbus, mb.CMD_PICK)
            modbus_s = time.perf_counter() - t0
            print(f"modbus: {a.n_modbus} picks in {modbus_s:.0f} s", file=sys.stderr, flush=True)
            ua_pick, ua_server, ua_read = asyncio.run(bench_opcua(cell, a.n_opcua, 4 * a.n_opcua))
            print("opcua done", file=sys.stderr, flush=True)
            rest_c, rest_s = bench_rest(cell, a.n_rest)
        finally:
            stop_served(cell.served)
    head = ("| path | n | client p50 (ms) | client p99 (ms) | client max (ms) | server-side pick p50 (ms) "
            "| overhead p50 / p99 (ms) |\n| --- | --- | --- | --- | --- | --- | --- |")
    rows = [
        row("Modbus TCP pick: PLC write -> result ready (poll 1 ms)", pick_c, pick_s),
        row("Modbus TCP idle request (command 0): protocol round trip", idle_c, None),
        row("OPC UA Cell.Pick(1) method call", ua_pick, ua_server),
        row("OPC UA read of one status variable", ua_read, None),
        row("**peer**: REST POST /pick (httpx, same cell, same run)", rest_c, rest_s),
    ]
    over = {
        "modbus": pct([c - s for c, s in zip(pick_c, pick_s, strict=True)], 50),
        "opcua": pct([c - s for c, s in zip(ua_pick, ua_server, strict=True)], 50),
        "rest": pct([c - s for c, s in zip(rest_c, rest_s, strict=True)], 50),
    }
    text = "\n".join([
        "# PLC front ends: Modbus TCP handshake and OPC UA method-call latency",
        "",
        f"Machine: {os.cpu_count()} cores (shared with other work; load varies). One `cellctl serve` of the "
        "virtual cell on loopback, true calibrations, recipe 1 = the bracket; every pick finds it. "
        "Produced by `bench/plc.py`.",
        "",
        head, *rows,
        "",
        f"Failed requests: Modbus picks {pick_fail}/{len(pick_c)}, Modbus idle {idle_fail}/{len(idle_c)}.",
        "",
        f"Overhead ratio to the REST peer (p50): Modbus {over['modbus'] / over['rest']:.2f}, "
        f"OPC UA {over['opcua'] / over['rest']:.2f} "
        f"(Modbus {over['modbus']:.2f} ms, OPC UA {over['opcua']:.2f} ms, REST {over['rest']:.2f} ms).",
        "",
        "The server-side pick time is the same pipeline for all three paths (grab -> locate -> convert); "
        "on the virtual cell it is dominated by the simulated camera rendering a frame, so the totals "
        "measure the renderer, and the overhead column measures the front end. The Modbus overhead "
        "includes the PLC's polling period (1 ms here; a PLC polling every cycle of 10 ms adds up to 10 ms). "
        "No latency target is set in the issue; none is claimed.",
        "",
    ])
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
