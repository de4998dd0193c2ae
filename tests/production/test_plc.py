"""A PLC runs production over Modbus TCP (pymodbus client): start with a recipe and a count, read the
production block until the run ends, read the counters; stop a run; refused without allow_motion."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import yaml
from pymodbus.client import ModbusTcpClient

from cellctl.plc import modbus_server as mb
from cellctl.plc.production import COUNTERS, ENDED, RESULTS, STATES
from cellctl.plc.requests import TEXT_MOTION_OFF
from tests.drivers.peers import free_port
from tests.support.production_cell import production_config, teach_recipe
from tests.support.served import start_served, stop_served

UNIT = 1


def block(client: ModbusTcpClient) -> dict[str, Any]:
    """The production block and STATUS / ECHO_SEQ / ERROR_TEXT (two reads: a read is at most 125 registers)."""
    head = client.read_holding_registers(mb.STATUS, count=10, device_id=UNIT)
    prod = client.read_holding_registers(mb.PRODUCTION, count=mb.END - mb.PRODUCTION, device_id=UNIT)
    assert not head.isError() and not prod.isError(), (head, prod)
    regs = {**{mb.STATUS + i: v for i, v in enumerate(head.registers)},
            **{mb.PRODUCTION + i: v for i, v in enumerate(prod.registers)}}

    def at(a: int) -> int:
        return int(regs[a])

    def i32(a: int) -> int:
        return mb.words_int32([at(a), at(a + 1)])

    p = mb.PRODUCTION
    counters = {k: i32(p + 4 + 2 * i) for i, k in enumerate(COUNTERS)}
    q = p + 4 + 2 * len(COUNTERS)
    return {"status": at(mb.STATUS), "echo": at(mb.ECHO_SEQ), "error_text": at(mb.ERROR_TEXT), "run_id": i32(p),
            "state": at(p + 2), "ended": at(p + 3), "counters": counters, "next_slot": i32(q),
            "last_result": at(q + 2), "last_slot": i32(q + 3), "cycle_median_ms": i32(q + 5),
            "sigma_um": i32(q + 7), "sigma_mdeg": i32(q + 9)}


def command(client: ModbusTcpClient, cmd: int, recipe: int, seq: int, count: int = 0) -> dict[str, Any]:
    assert not client.write_registers(mb.COMMAND, [cmd, recipe, seq, count], device_id=UNIT).isError()
    deadline = time.monotonic() + 30
    while True:
        b = block(client)
        if b["echo"] == seq and not b["status"] & mb.BUSY:
            return b
        assert time.monotonic() < deadline, b
        time.sleep(0.05)


def until(client: ModbusTcpClient, check: Any, timeout_s: float = 90.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        b = block(client)
        if check(b):
            return b
        assert time.monotonic() < deadline, b
        time.sleep(0.1)


def plc_config(tmp: Path, allow_motion: bool) -> tuple[Path, int]:
    path = production_config(tmp, count=3)
    cfg = yaml.safe_load(path.read_text())
    port = free_port()
    cfg["plc"] = {"modbus": {"enabled": True, "host": "127.0.0.1", "port": port, "unit_id": UNIT},
                  "allow_motion": allow_motion}
    path.write_text(yaml.safe_dump(cfg))
    return path, port


def test_a_plc_starts_a_run_reads_its_counters_and_stops_the_next(tmp_path: Path) -> None:
    path, port = plc_config(tmp_path, allow_motion=True)
    served = start_served(tmp_path, path)
    try:
        teach_recipe(served.client(timeout_s=60))
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as client:
            assert block(client)["run_id"] == 0  # no run yet
            done = command(client, 4, 1, 101, count=2)
            assert done["status"] & mb.DONE and done["run_id"] >= 1, done
            end = until(client, lambda b: b["ended"] != 0)
            assert end["ended"] == ENDED["count_reached"] and end["state"] == STATES["complete"], end
            c = end["counters"]
            assert c["placed"] == 2 and c["picked"] == 2 and c["grip_failures"] == 0, c
            assert end["next_slot"] == 2 and end["last_result"] == RESULTS["placed"] and end["last_slot"] == 1
            assert end["cycle_median_ms"] > 0 and 0 <= end["sigma_um"] < 1000 and 0 <= end["sigma_mdeg"] < 1000
            # A second run until the area is empty, stopped by the PLC after the cycle in progress.
            first = end["run_id"]
            assert command(client, 4, 1, 102)["status"] & mb.DONE
            until(client, lambda b: b["run_id"] == first + 1 and b["state"] == STATES["running"])
            assert command(client, 7, 1, 103)["status"] & mb.DONE
            stopped = until(client, lambda b: b["ended"] != 0)
            assert stopped["ended"] == ENDED["stopped"] and stopped["state"] == STATES["stopped"], stopped
            assert stopped["counters"]["placed"] <= 1
        rest = served.client().get("/production").json()
        assert rest["run_id"] == first + 1 and rest["ended_because"] == "stopped"
    finally:
        stop_served(served)


def test_without_allow_motion_the_plc_cannot_start_a_run(tmp_path: Path) -> None:
    path, port = plc_config(tmp_path, allow_motion=False)
    served = start_served(tmp_path, path)
    try:
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as client:
            refused = command(client, 4, 1, 201, count=1)
            assert refused["status"] & mb.ERROR and refused["error_text"] == TEXT_MOTION_OFF, refused
            assert refused["run_id"] == 0
    finally:
        stop_served(served)


def test_a_plc_runs_production_over_opc_ua(tmp_path: Path) -> None:
    import asyncio

    from asyncua import Client, ua

    # 6 parts: the second run (until the area is empty) still has parts when the Stop comes
    path = production_config(tmp_path, count=6)
    cfg = yaml.safe_load(path.read_text())
    port = free_port()
    cfg["plc"] = {"opcua": {"enabled": True, "host": "127.0.0.1", "port": port}, "allow_motion": True}
    path.write_text(yaml.safe_dump(cfg))
    served = start_served(tmp_path, path)
    try:
        teach_recipe(served.client(timeout_s=60))

        async def run() -> None:
            async with Client(f"opc.tcp://127.0.0.1:{port}/cellctl/", timeout=30) as client:
                idx = await client.get_namespace_index("urn:cellctl")
                cell = await client.nodes.objects.get_child(f"{idx}:Cell")

                async def var(name: str) -> Any:
                    return await (await cell.get_child(f"{idx}:{name}")).read_value()

                assert await var("ProductionRunId") == 0
                run_id = await cell.call_method(f"{idx}:StartProduction", ua.Variant(1, ua.VariantType.Int32),
                                                ua.Variant(2, ua.VariantType.Int32))
                assert run_id >= 1
                deadline = time.monotonic() + 90
                while await var("ProductionState") != "complete":
                    assert time.monotonic() < deadline, await var("ProductionState")
                    await asyncio.sleep(0.2)
                assert await var("ProductionEndedBecause") == "count_reached"
                assert await var("ProductionPlaced") == 2 and await var("ProductionNextSlot") == 2
                assert await var("ProductionLastResult") == "placed"
                assert 0 <= await var("ProductionLastSigmaMm") < 1.0
                second = await cell.call_method(f"{idx}:StartProduction", ua.Variant(1, ua.VariantType.Int32),
                                                ua.Variant(0, ua.VariantType.Int32))
                assert second == run_id + 1
                # The variables refresh every 0.1 s: until they show the second run they read the first's end.
                while await var("ProductionRunId") != second:
                    assert time.monotonic() < deadline
                    await asyncio.sleep(0.05)
                await cell.call_method(f"{idx}:StopProduction")
                while await var("ProductionEndedBecause") == "":
                    assert time.monotonic() < deadline
                    await asyncio.sleep(0.2)
                assert await var("ProductionState") == "stopped"

        asyncio.run(run())
    finally:
        stop_served(served)
