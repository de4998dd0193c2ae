"""A PLC pick WITH robot motion against the motion owner and the Stop latch, on the virtual cell.

The cell (true calibrations, recipe 1 = the bracket, ``plc.allow_motion: true``) is the app in this
process with its real-time virtual robot (``tests.support.served_plc.in_process_plc``); the PLC is a
pymodbus client (command 3) and an asyncua client (``PickAndMove``) on loopback; Stop, resume and the
competing moves are REST calls to the app.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaStatusCodeError
from pymodbus.client import ModbusTcpClient

from cellctl.plc import modbus_server as mb
from cellctl.plc.requests import (
    CLASS_BUSY,
    CLASS_SETUP,
    CLASS_STOPPED,
    TEXT_MOTION_OFF,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
)
from tests.plc.conftest import RECIPE, PlcApp
from tests.plc.test_modbus_server import UNIT, Answer, message, next_seq, read_answer, request, wait_answer
from tests.plc.test_opcua_server import CLIENT_OPTIONS, cell_node, read
from tests.support.served_plc import in_process_plc


async def settled(node: Any, idx: int, name: str, expected: Any, timeout_s: float = 15.0) -> bool:
    """Poll a live variable until it reads ``expected`` (it is refreshed every 0.1 s)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if await read(node, idx, name) == expected:
            return True
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.05)

async def owned_by(node: Any, idx: int, what: str, timeout_s: float = 15.0) -> bool:
    """Poll ``RobotMotionOwner`` until it names ``what`` (it is refreshed every 0.1 s)."""
    deadline = time.monotonic() + timeout_s
    while what not in str(await read(node, idx, "RobotMotionOwner")):
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.05)
    return True


STOPPED_TEXT = "robot stopped: an engineer must resume it"
APPROACH_MM = 40.0 + 5.0  # the recipe's approach height above its grasp height (tests/plc/conftest.py)


class MotionCell:
    """The cell (``plc.allow_motion: true``), its PLC ports and a REST client with the engineer's token."""

    def __init__(self, tmp: Path) -> None:
        self._stack = ExitStack()
        try:
            cell = self._stack.enter_context(in_process_plc(tmp, allow_motion=True))
            self.modbus_port, self.opcua_port, self.opcua_url = cell.modbus_port, cell.opcua_port, cell.opcua_url
            self.part_x_mm, self.part_y_mm = cell.part_x_mm, cell.part_y_mm
            self.http = self._stack.enter_context(cell.http())
            self.home = self.pose_ur()
        except BaseException:
            self._stack.close()
            raise

    def pose_ur(self) -> dict[str, float]:
        r = self.http.get("/robots/robot0/state")
        assert r.status_code == 200, r.text
        pose: dict[str, float] = r.json()["pose_ur"]
        return pose

    def state(self) -> dict[str, Any]:
        out: dict[str, Any] = self.http.get("/robots/robot0/state").json()
        return out

    def go_home(self) -> None:
        r = self.http.post("/robots/robot0/move", json={"pose_ur": self.home, "speed_m_s": 0.25})
        assert r.status_code == 200, r.text

    def stop(self) -> None:
        r = self.http.post("/robots/robot0/stop")
        assert r.status_code == 200 and r.json()["latched"] is True, r.text

    def resume(self) -> None:
        r = self.http.post("/robots/robot0/resume")
        assert r.status_code == 200 and r.json()["latched"] is False, r.text

    def modbus(self) -> ModbusTcpClient:
        client = ModbusTcpClient("127.0.0.1", port=self.modbus_port, timeout=5, retries=0)
        assert client.connect()
        return client

    def at_pick_approach(self) -> bool:
        p = self.pose_ur()
        return (math.hypot(p["x_m"] * 1e3 - self.part_x_mm, p["y_m"] * 1e3 - self.part_y_mm) < 1.0
                and abs(p["z_m"] * 1e3 - APPROACH_MM) < 1.0)

    def close(self) -> None:
        self._stack.close()


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotionCell]:
    c = MotionCell(tmp_path_factory.mktemp("plc-motion"))
    try:
        yield c
    finally:
        c.close()


@pytest.fixture
def at_home(cell: MotionCell) -> Iterator[MotionCell]:
    """Each test starts with the robot free, not latched, at its capture pose (and leaves it so)."""
    yield cell
    cell.http.post("/robots/robot0/resume")
    cell.go_home()


def picked(client: ModbusTcpClient) -> int:
    return int(client.read_holding_registers(mb.PICKED, count=1, device_id=UNIT).registers[0])


def modbus_pick_move(client: ModbusTcpClient, timeout_s: float = 90.0) -> tuple[Answer, str]:
    seq = next_seq()
    request(client, mb.CMD_PICK_MOVE, RECIPE, seq)
    a = wait_answer(client, seq, timeout_s)
    return a, message(client)


def wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s} s: {what}")
        time.sleep(0.02)


def test_modbus_pick_with_motion_obeys_the_latch(at_home: MotionCell) -> None:
    cell = at_home
    with cell.modbus() as client:
        assert read_answer(client).status & (mb.ROBOT_LATCHED | mb.ROBOT_OWNED) == 0
        # Free: the robot picks the best part and ends above it, at the approach height.
        a, msg = modbus_pick_move(client)
        assert a.status & mb.DONE, (a, msg)
        assert a.command == mb.CMD_PICK_MOVE and a.reported >= 1 and picked(client) == 1
        assert cell.at_pick_approach(), cell.pose_ur()
        moves = [e for e in cell.http.get("/audit", params={"action": "robot.move"}).json()
                 if e["who"] == "plc:modbus"][:3]
        assert [e["result"] for e in moves] == ["ok"] * 3
        cell.go_home()

        # Latched by a Stop: the bit shows at once, the pick is refused and nothing moves.
        cell.stop()
        assert read_answer(client).status & mb.ROBOT_LATCHED
        before = cell.pose_ur()
        a, msg = modbus_pick_move(client)
        assert a.status & mb.ERROR and (a.error_code, a.error_text) == (CLASS_STOPPED, TEXT_ROBOT_STOPPED), a
        assert msg.startswith(STOPPED_TEXT) and picked(client) == 0
        assert cell.pose_ur() == pytest.approx(before, abs=1e-6)

        # Resumed by the engineer: the bit clears and the pick works again.
        cell.resume()
        assert not read_answer(client).status & mb.ROBOT_LATCHED
        a, msg = modbus_pick_move(client)
        assert a.status & mb.DONE, (a, msg)
        assert picked(client) == 1 and cell.at_pick_approach()


def test_modbus_pick_with_motion_stopped_midway(at_home: MotionCell) -> None:
    cell = at_home
    with cell.modbus() as client:
        seq = next_seq()
        request(client, mb.CMD_PICK_MOVE, RECIPE, seq)
        wait_for(lambda: read_answer(client).status & mb.ROBOT_OWNED, 30.0, "the PLC pick owns the robot")
        wait_for(lambda: cell.state()["moving"], 60.0, "the robot moves")
        cell.stop()
        a = wait_answer(client, seq, 30.0)
        assert a.status & mb.ERROR and a.error_text == TEXT_ROBOT_STOPPED, (a, message(client))
        assert message(client).startswith(STOPPED_TEXT)
        assert read_answer(client).status & mb.ROBOT_LATCHED and not read_answer(client).status & mb.ROBOT_OWNED
        halted = cell.pose_ur()
        time.sleep(0.5)
        assert cell.pose_ur() == pytest.approx(halted, abs=1e-6)  # standing still, not at the pick
        assert not cell.at_pick_approach()


def test_modbus_pick_with_motion_while_another_caller_moves_the_robot(at_home: MotionCell) -> None:
    cell = at_home
    slow = {"pose_ur": {**cell.home, "z_m": cell.home["z_m"] - 0.1}, "speed_m_s": 0.02}  # 5 s
    result: dict[str, httpx.Response] = {}
    mover = threading.Thread(target=lambda: result.update(r=cell.http.post("/robots/robot0/move", json=slow)))
    with cell.modbus() as client:
        mover.start()
        wait_for(lambda: read_answer(client).status & mb.ROBOT_OWNED, 10.0, "the REST move owns the robot")
        a, msg = modbus_pick_move(client)
        assert a.status & mb.ERROR and (a.error_code, a.error_text) == (CLASS_BUSY, TEXT_ROBOT_BUSY), (a, msg)
        assert "busy" in msg
        mover.join(30.0)
    assert result["r"].status_code == 200, result["r"].text  # the first mover was not disturbed


def test_opcua_pick_and_move_obeys_owner_and_latch(at_home: MotionCell) -> None:
    cell = at_home

    async def run() -> None:
        async with Client(cell.opcua_url, **CLIENT_OPTIONS) as client:
            node, idx = await cell_node(client)
            arg = ua.Variant(RECIPE, ua.VariantType.Int32)
            assert await read(node, idx, "RobotLatched") is False
            assert await settled(node, idx, "RobotMotionOwner", "")  # the last test's moves have ended
            count, poses, reachable, picked_index = await node.call_method(f"{idx}:PickAndMove", arg)
            assert count >= 1 and picked_index == 0 and reachable[0] is True
            assert math.hypot(poses[0] - cell.part_x_mm, poses[1] - cell.part_y_mm) < 0.5
            assert await asyncio.to_thread(cell.at_pick_approach)
            await asyncio.to_thread(cell.go_home)

            await asyncio.to_thread(cell.stop)
            assert await settled(node, idx, "RobotLatched", True)  # the variable follows within 0.1 s
            with pytest.raises(UaStatusCodeError) as e:
                await node.call_method(f"{idx}:PickAndMove", arg)
            assert e.value.code == ua.StatusCodes.BadRequestNotAllowed
            assert (await read(node, idx, "LastError")).startswith(STOPPED_TEXT)
            assert await read(node, idx, "LastErrorCode") == TEXT_ROBOT_STOPPED

            await asyncio.to_thread(cell.resume)
            assert await settled(node, idx, "RobotLatched", False)
            slow = {"pose_ur": {**cell.home, "z_m": cell.home["z_m"] - 0.1}, "speed_m_s": 0.02}
            mover = asyncio.create_task(asyncio.to_thread(cell.http.post, "/robots/robot0/move", json=slow))
            # the REST move owns the robot once its request is through (polled, not a fixed second: under load
            # the request may take longer to get there)
            assert await owned_by(node, idx, "linear move")
            assert "linear move" in await read(node, idx, "RobotMotionOwner")
            with pytest.raises(UaStatusCodeError) as e:
                await node.call_method(f"{idx}:PickAndMove", arg)
            assert e.value.code == ua.StatusCodes.BadLocked
            assert (await mover).status_code == 200
            await asyncio.to_thread(cell.go_home)
            _, _, _, picked_index = await node.call_method(f"{idx}:PickAndMove", arg)
            assert picked_index == 0 and await asyncio.to_thread(cell.at_pick_approach)

    asyncio.run(run())


def test_pick_with_motion_is_off_unless_the_config_allows_it(plc_app: PlcApp) -> None:
    client = ModbusTcpClient("127.0.0.1", port=plc_app.modbus_port, timeout=5, retries=0)
    assert client.connect()
    with client, plc_app.http() as http:
        before = http.get("/robots/robot0/state").json()["pose_ur"]
        a, msg = modbus_pick_move(client)
        assert a.status & mb.ERROR and (a.error_code, a.error_text) == (CLASS_SETUP, TEXT_MOTION_OFF), a
        assert "plc.allow_motion" in msg
        assert http.get("/robots/robot0/state").json()["pose_ur"] == pytest.approx(before, abs=1e-6)

    async def opcua() -> None:
        async with Client(plc_app.opcua_url, **CLIENT_OPTIONS) as c:
            node, idx = await cell_node(c)
            with pytest.raises(UaStatusCodeError) as e:
                await node.call_method(f"{idx}:PickAndMove", ua.Variant(RECIPE, ua.VariantType.Int32))
            assert e.value.code == ua.StatusCodes.BadNotExecutable

    asyncio.run(opcua())


def test_the_documented_error_texts_are_the_served_ones() -> None:
    from cellctl.plc.requests import ERROR_TEXTS

    doc = (Path(__file__).resolve().parents[2] / "docs" / "plc-modbus.md").read_text()
    table = doc.split("## Error texts (ERROR_TEXT)", 1)[1].split("\n## ", 1)[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()
            if line.startswith("| ") and line[2].isdigit()]
    documented = {int(index): (int(cls), text) for index, cls, text in rows}
    assert documented.keys() == ERROR_TEXTS.keys()
    for index, (cls, text) in ERROR_TEXTS.items():
        assert documented[index][0] == cls and documented[index][1].startswith(text), (index, documented[index])
