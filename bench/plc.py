"""PLC front-end benchmark (issues 9 and 35): a pick's request -> answer latency through every front end
against the Modbus path in the same run, and Stop latency while every front end is polled at its fastest.

One ``cellctl serve`` of the virtual cell (true calibrations active, the bracket taught as recipe 1, as
tests/plc prepares it) with every PLC front end on loopback: Modbus TCP, the OPC UA model (``Cell.Pick``),
EtherNet/IP (pylogix as the Logix PLC) and the robot socket (a plain TCP client as the robot program),
plus the REST peer. Each round runs one pick through every path, the order rotated each round, so all
see the same machine load:

- **Modbus** (the reference): one FC16 (COMMAND, RECIPE, SEQUENCE), then FC3 polls of 10..109 every
  1 ms until ECHO_SEQ is the sequence.
- **OPC UA**: ``Cell.Pick(1)`` (asyncua's client): the method call's round trip.
- **OPC UA Machine Vision** (OPC 40100): ``StartSingleJob`` of the prepared recipe 1 (asyncua's client,
  after ``SelectModeAutomatic`` and ``PrepareRecipe``), until its ``ResultReadyEventType`` event arrives
  (a subscription publishing every 10 ms: what a PLC does, at a faster interval than most PLCs ask).
- **EtherNet/IP**: pylogix writes CC_Command, CC_Recipe, CC_Sequence, then polls CC_EchoSeq every 1 ms and
  reads CC_Picks: what a Logix PLC's MSG instructions do.
- **robot socket**: ``PICK 1`` -> the ``OK ...`` line.
- **REST** ``POST /pick`` (peer, not a PLC front end).

Then **Stop under polling**: one process per front end (a PLC each) polls it as fast as it answers (Modbus FC3 of 100
registers, an OPC UA variable read, a pylogix read of CC_Status, a socket STATUS line), and meanwhile
``POST /robots/robot0/stop`` (then resume) is timed; the same without polling as the baseline. Target:
every pick path's median within 1.2x the Modbus median; Stop within 100 ms (the safety target).

Run: ``.venv/bin/python bench/plc.py [--rounds 40] [--stops 20] [--out bench/results/plc.md]``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from asyncua import ua  # noqa: E402
from asyncua.sync import Client  # noqa: E402
from pylogix import PLC  # noqa: E402
from pymodbus.client import ModbusTcpClient  # noqa: E402

from cellctl.plc import modbus_server as mb  # noqa: E402
from cellctl.plc.opcua_mv.nodeset import NAMESPACE_MV  # noqa: E402
from cellctl.plc.opcua_server import NAMESPACE  # noqa: E402
from tests.support.served import stop_served  # noqa: E402
from tests.support.served_plc import RECIPE, PlcCell, start_all_front_ends  # noqa: E402

POLL_S = 0.001
ENIP_POLL_S = POLL_S
"""EtherNet/IP polls CC_EchoSeq every 1 ms, as Modbus polls ECHO_SEQ (the fast path answers a read in microseconds;
with cpppo parsing every frame it was 10 ms, and still 4.5x Modbus)."""
MV_PUBLISH_MS = 10
"""The ResultReady subscription's publishing interval: the event waits up to this long after the job's end."""
RATIO_TARGET = 1.2
STOP_TARGET_MS = 100.0


def pct(values: Sequence[float], q: float) -> float:
    s = sorted(values)
    if not s:
        return float("nan")
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


class Paths:
    """One client per front end, each doing a pick the way its PLC (or robot) would; returns found picks."""

    def __init__(self, cell: PlcCell) -> None:
        self.modbus = ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=30, retries=0)
        assert self.modbus.connect()
        self.seq = 0
        self.ua = Client(cell.opcua_url, timeout=60)
        self.ua.connect()
        idx = self.ua.get_namespace_index(NAMESPACE)
        self.ua_cell = self.ua.nodes.objects.get_child(f"{idx}:Cell")
        self.ua_pick = self.ua_cell.get_child(f"{idx}:Pick")
        self.ua_status = self.ua_cell.get_child(f"{idx}:RobotLatched")
        self.mv = MachineVision(self.ua)
        self.enip = PLC()
        self.enip.IPAddress, self.enip.Port, self.enip.SocketTimeout = "127.0.0.1", cell.enip_port, 30.0
        self.enip_seq = 0
        self.sock = socket.create_connection(("127.0.0.1", cell.robot_socket_port), timeout=60)
        self.http = cell.served.client(timeout_s=60)

    def close(self) -> None:
        self.modbus.close()
        self.mv.close()
        self.ua.disconnect()
        self.enip.Close()
        self.sock.close()
        self.http.close()

    def modbus_pick(self) -> int:
        self.seq = self.seq % 65535 + 1
        self.modbus.write_registers(mb.COMMAND, [mb.CMD_PICK, RECIPE, self.seq], device_id=1)
        while True:
            r = self.modbus.read_holding_registers(mb.STATUS, count=100, device_id=1).registers
            if r[mb.ECHO_SEQ - mb.STATUS] == self.seq:
                return int(r[mb.PICKS_REPORTED - mb.STATUS]) if r[0] & mb.DONE else 0
            time.sleep(POLL_S)

    def opcua_pick(self) -> int:
        count, _, _ = self.ua_cell.call_method(self.ua_pick, ua.Variant(RECIPE, ua.VariantType.Int32))
        return int(count)

    def mv_pick(self) -> int:
        return self.mv.job()

    def enip_pick(self) -> int:
        self.enip_seq += 1
        self.enip.Write("CC_Command", 1)
        self.enip.Write("CC_Recipe", RECIPE)
        self.enip.Write("CC_Sequence", 100000 + self.enip_seq)
        while self.enip.Read("CC_EchoSeq").Value != 100000 + self.enip_seq:
            time.sleep(ENIP_POLL_S)
        n = int(self.enip.Read("CC_PicksReported").Value)
        self.enip.Read("CC_Picks", 8 * n) if n else None
        return n

    def socket_pick(self) -> int:
        self.sock.sendall(f"PICK {RECIPE}\n".encode())
        return 1 if _line(self.sock).startswith("OK ") else 0

    def rest_pick(self) -> int:
        r = self.http.post("/pick", json={"recipe_id": RECIPE})
        return len(r.json()["picks"]) if r.status_code == 200 else 0


class MachineVision:
    """OPC 40100's VisionSystem as a PLC drives it: automatic mode, recipe 1 prepared, one StartSingleJob at a time,
    the answer its ResultReadyEventType event (the picks' JSON in ResultContent)."""

    def __init__(self, client: Client) -> None:
        deadline = time.monotonic() + 60
        ns = client.get_namespace_index(NAMESPACE_MV)
        vs = client.nodes.objects.get_child(f"{ns}:VisionSystem")
        vsm = vs.get_child(f"{ns}:VisionStateMachine")
        while (vsm.get_child("0:CurrentState").read_value().Text or "") != "Operational":
            assert time.monotonic() < deadline, "VisionSystem not Operational within 60 s"
            time.sleep(0.2)
        client.load_data_type_definitions()
        self.auto = vsm.get_child(f"{ns}:AutomaticModeStateMachine")
        self.start = f"{ns}:StartSingleJob"
        vsm.call_method(f"{ns}:SelectModeAutomatic")
        recipe = ua.RecipeIdExternalDataType(Id=str(RECIPE))  # type: ignore[attr-defined]
        vs.get_child(f"{ns}:RecipeManagement").call_method(f"{ns}:PrepareRecipe", recipe, ua.Variant())
        self.results: dict[str, str] = {}
        self.arrived = threading.Condition()
        self.sub = client.create_subscription(MV_PUBLISH_MS, self)
        self.sub.subscribe_events(vs, client.get_node(ua.NodeId(ua.Int32(1024), ua.Int16(ns))))

    def event_notification(self, event: object) -> None:
        """asyncua's subscription handler: a ResultReadyEventType event (in the client's thread)."""
        fields = event.get_event_props_as_fields_dict()  # type: ignore[attr-defined]
        job = fields.get("JobId")
        key = str(getattr(job.Value, "Id", job.Value)) if job is not None else ""
        content: object = fields["ResultContent"].Value if "ResultContent" in fields else ""
        while isinstance(content, (list, ua.Variant)):  # one String, in an array of Variants
            content = (content[0] if content else "") if isinstance(content, list) else content.Value
        with self.arrived:
            self.results[key] = str(content)
            self.arrived.notify_all()

    def status_change_notification(self, status: object) -> None:
        print(f"OPC UA Machine Vision subscription: status {status}", file=sys.stderr, flush=True)

    def job(self) -> int:
        empty = ua.Variant()
        job_id, _status = self.auto.call_method(self.start, empty, empty, empty, empty,
                                                ua.Variant([], ua.VariantType.Variant))
        key = str(job_id.Id)
        with self.arrived:
            assert self.arrived.wait_for(lambda: key in self.results, 60), f"no result for job {key}"
            content = self.results.pop(key)
        try:
            return len(json.loads(content).get("picks") or [])
        except (ValueError, AttributeError):
            return 0

    def close(self) -> None:
        self.sub.delete()


def _line(s: socket.socket) -> str:
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(4096)
        if not chunk:
            break
        buf += chunk
    return buf.decode("ascii", "replace")


PATHS = ("modbus", "opcua", "mv", "enip", "socket", "rest")
NAMES = {"modbus": "Modbus TCP: FC16 request, FC3 poll every 1 ms until ECHO_SEQ (reference)",
         "opcua": "OPC UA Cell.Pick(1) method call (asyncua client)",
         "mv": "OPC UA Machine Vision: StartSingleJob (recipe 1 prepared) until its ResultReady event (asyncua client, "
              "publishing every 10 ms)",
         "enip": "EtherNet/IP: pylogix writes the request tags, polls CC_EchoSeq every 1 ms, reads CC_Picks",
         "socket": "robot socket: `PICK 1` -> `OK ...` line",
         "rest": "**peer**: REST POST /pick (not a PLC front end)"}


def picks(paths: Paths, rounds: int) -> tuple[dict[str, list[float]], dict[str, int]]:
    calls: dict[str, Callable[[], int]] = {"modbus": paths.modbus_pick, "opcua": paths.opcua_pick,
                                          "mv": paths.mv_pick,
                                          "enip": paths.enip_pick, "socket": paths.socket_pick,
                                          "rest": paths.rest_pick}
    for name in PATHS:  # one warm-up call per path
        calls[name]()
    ms: dict[str, list[float]] = {k: [] for k in PATHS}
    empty = dict.fromkeys(PATHS, 0)
    t0 = time.perf_counter()
    for i in range(rounds):
        order = PATHS[i % len(PATHS):] + PATHS[: i % len(PATHS)]
        for name in order:
            t1 = time.perf_counter()
            n = calls[name]()
            ms[name].append((time.perf_counter() - t1) * 1e3)
            empty[name] += 0 if n >= 1 else 1
        if (i + 1) % 10 == 0:
            print(f"{i + 1} rounds in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return ms, empty


def _poll(name: str, ports: dict[str, Any], stop: Any, count: Any) -> None:
    """One PLC polling front end ``name`` as fast as it answers until ``stop`` (run in its own process);
    ``watch``: a PLC watching the cell, a Modbus FC3 of STATUS every 1 ms. At the lowest CPU priority: a PLC is
    another machine, its CPU is not the service's (on this 2-core machine four clients polling flat out would
    otherwise take the cores from the service they measure)."""
    os.nice(19)
    if name in ("modbus", "watch"):
        with ModbusTcpClient("127.0.0.1", port=ports["modbus"], timeout=10, retries=0) as c:
            while not stop.is_set():
                c.read_holding_registers(mb.STATUS, count=100 if name == "modbus" else 10, device_id=1)
                count.value += 1
                if name == "watch":
                    time.sleep(POLL_S)
    elif name == "opcua":
        ua_client = Client(ports["opcua"], timeout=30)
        ua_client.connect()
        try:
            idx = ua_client.get_namespace_index(NAMESPACE)
            node = ua_client.nodes.objects.get_child(f"{idx}:Cell").get_child(f"{idx}:RobotLatched")
            while not stop.is_set():
                node.read_value()
                count.value += 1
        finally:
            ua_client.disconnect()
    elif name == "enip":
        with PLC() as plc:
            plc.IPAddress, plc.Port = "127.0.0.1", ports["enip"]
            while not stop.is_set():
                plc.Read("CC_Status")
                count.value += 1
    else:
        with socket.create_connection(("127.0.0.1", ports["robot_socket"]), timeout=10) as s:
            while not stop.is_set():
                s.sendall(b"STATUS\n")
                _line(s)
                count.value += 1


POLLERS = ("modbus", "opcua", "enip", "robot_socket")


class Pollers:
    """One process per front end (``only`` those named; ``watch``: the 1 ms status poll), each a PLC polling it as
    fast as it answers: separate
    processes, as separate PLCs are separate machines (threads in this process would compete with the timed Stop's
    client for this process's interpreter lock, and measure that)."""

    def __init__(self, cell: PlcCell, only: Sequence[str] = POLLERS) -> None:
        ctx = multiprocessing.get_context("spawn")
        ports = {"modbus": cell.modbus_port, "opcua": cell.opcua_url, "enip": cell.enip_port,
                 "robot_socket": cell.robot_socket_port}
        self.stop = ctx.Event()
        self.counts = {n: ctx.Value("q", 0) for n in only}
        self.procs = [ctx.Process(target=_poll, args=(n, ports, self.stop, c), name=f"poll-{n}")
                      for n, c in self.counts.items()]
        for p in self.procs:
            p.start()

    def wait_polling(self, timeout_s: float = 60.0) -> None:
        """Until every poller has been answered at least once (its process imported and connected)."""
        deadline = time.monotonic() + timeout_s
        while any(c.value == 0 for c in self.counts.values()):
            assert time.monotonic() < deadline, "a poller never got an answer"
            time.sleep(0.1)

    def snapshot(self) -> dict[str, int]:
        return {n: int(c.value) for n, c in self.counts.items()}

    def close(self) -> None:
        self.stop.set()
        for p in self.procs:
            p.join(30)


def stops(cell: PlcCell, n: int) -> list[float]:
    """``n`` timed POST /robots/robot0/stop (each followed by a resume, not timed)."""
    out = []
    with cell.served.client(timeout_s=30) as http:
        for _ in range(n):
            t0 = time.perf_counter()
            r = http.post("/robots/robot0/stop")
            out.append((time.perf_counter() - t0) * 1e3)
            assert r.status_code == 200, r.text
            assert http.post("/robots/robot0/resume").status_code == 200
            time.sleep(0.05)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=40, help="rounds of one pick per path")
    p.add_argument("--stops", type=int, default=20, help="timed Stops, idle and under polling each")
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "plc.md"))
    a = p.parse_args(argv)
    a.load_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-plc-") as tmp:
        t_start = time.perf_counter()
        cell = start_all_front_ends(Path(tmp))
        print(f"served cell ready in {time.perf_counter() - t_start:.1f} s", file=sys.stderr, flush=True)
        try:
            paths = Paths(cell)
            try:
                quiet = picks(paths, a.rounds)
                watching = Pollers(cell, ["watch"])
                try:
                    watching.wait_polling()
                    watched = picks(paths, a.rounds)
                finally:
                    watching.close()
            finally:
                paths.close()
            idle_stop = stops(cell, a.stops)
            polling = Pollers(cell)
            try:
                polling.wait_polling()
                time.sleep(1.0)
                t_poll = time.perf_counter()
                before = polling.snapshot()
                polled_stop = stops(cell, a.stops)
                after = polling.snapshot()
                rates = {k: (after[k] - before[k]) / (time.perf_counter() - t_poll) for k in after}
            finally:
                polling.close()
        finally:
            stop_served(cell.served)
    a.load_end = os.getloadavg()[0]
    write(a, quiet, watched, idle_stop, polled_stop, rates)


Picks = tuple[dict[str, list[float]], dict[str, int]]


def pick_table(ms: dict[str, list[float]], empty: dict[str, int]) -> list[str]:
    ref = pct(ms["modbus"], 50)
    lines = ["| path | n | p50 (ms) | p99 (ms) | max (ms) | p50 / Modbus p50 | within target | without a pick |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in PATHS:
        v = ms[name]
        ratio = pct(v, 50) / ref
        target = "-" if name in ("modbus", "rest") else ("yes" if ratio <= RATIO_TARGET else "**no**")
        lines.append(f"| {NAMES[name]} | {len(v)} | {pct(v, 50):.1f} | {pct(v, 99):.1f} | {max(v):.1f} | "
                     f"{ratio:.2f} | {target} | {empty[name]} |")
    return lines


def write(a: argparse.Namespace, quiet: Picks, watched: Picks, idle_stop: list[float],
          polled_stop: list[float], rates: dict[str, float]) -> None:
    lines = [
        "# PLC front ends: a pick through each, against the Modbus path; Stop while every front end is polled",
        "",
        f"Machine: {os.cpu_count()} cores (shared with other work; load varies). One `cellctl serve` of the virtual "
        "cell on loopback with every PLC front end (Modbus TCP, OPC UA, EtherNet/IP, robot socket), true "
        "calibrations, recipe 1 = the bracket. Produced by "
        f"`.venv/bin/python bench/plc.py --rounds {a.rounds} --stops {a.stops}`. Load average (1 min) "
        f"{a.load_start:.1f} at the start, {a.load_end:.1f} at the end: the machine is shared with other work, "
        "so every row is slower than on a quiet machine; the ratios compare paths run in the same rounds.",
        "",
        "Each round runs one pick through every path (order rotated each round), so the paths share the load. "
        f"Target: each PLC front end's median within {RATIO_TARGET}x the Modbus median.",
        "",
        "### With a PLC watching the cell (a Modbus status poll every 1 ms in the background, as on a line)",
        "",
        *pick_table(*watched),
        "",
        "### A quiet service (nothing but the request itself)",
        "",
        *pick_table(*quiet),
        "",
        "The pick itself (grab a rendered 1280x960 frame, search, convert) dominates every path; the ratios "
        "measure what each front end adds. The polled paths (Modbus, EtherNet/IP) include up to one polling "
        "period (1 ms here; a PLC polling every task cycle adds up to its cycle).",
        "",
        "## Stop (`POST /robots/robot0/stop`) while every front end is polled at its fastest "
        f"(target {STOP_TARGET_MS:.0f} ms)",
        "",
        "| load | n | p50 (ms) | p95 (ms) | max (ms) | all within target |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for label, v in (("idle (no polling)", idle_stop), ("every front end polled", polled_stop)):
        ok = "yes" if max(v) <= STOP_TARGET_MS else f"**no** ({sum(1 for x in v if x > STOP_TARGET_MS)} over)"
        lines.append(f"| {label} | {len(v)} | {pct(v, 50):.1f} | {pct(v, 95):.1f} | {max(v):.1f} | {ok} |")
    lines += ["", "Polling rates during the polled Stops (requests/s, one client each): "
              + ", ".join(f"{k} {r:.0f}" for k, r in rates.items()) + "."]
    Path(a.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
