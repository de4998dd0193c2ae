"""The Modbus TCP server of the virtual cell (the app in this process), driven by a pymodbus client as the PLC."""

from __future__ import annotations

import math
import socket
import time
from dataclasses import dataclass

from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import ExceptionResponse

from cellctl.plc import modbus_server as mb
from cellctl.plc.requests import (
    CLASS_REQUEST,
    CLASS_SETUP,
    TEXT_UNKNOWN_COMMAND,
    TEXT_UNKNOWN_RECIPE,
)
from tests.plc.conftest import RECIPE, PlcApp, PlcCell

UNIT = 1
_seq = [100]


def next_seq() -> int:
    _seq[0] += 1
    return _seq[0]


@dataclass
class Answer:
    status: int
    echo: int
    active: int
    error_code: int
    error_text: int
    command: int
    reported: int
    found: int
    verify_passed: int
    refused_seq: int
    drift_px: float
    drift_mm: float
    latency_ms: float
    picks: list[dict[str, float]]

    @staticmethod
    def parse(r: list[int]) -> Answer:
        """Decode a read of 10..109 the way a PLC program would."""
        def at(addr: int) -> int:
            return r[addr - mb.STATUS]

        def i32(addr: int) -> int:
            return mb.words_int32(r[addr - mb.STATUS : addr - mb.STATUS + 2])

        picks = []
        for k in range(at(mb.PICKS_REPORTED)):
            b = mb.PICKS + mb.PICK_STRIDE * k
            picks.append({"x_mm": i32(b) / 100, "y_mm": i32(b + 2) / 100, "z_mm": i32(b + 4) / 100,
                          "yaw_deg": i32(b + 6) / 1000, "score": at(b + 8) / 1000, "reachable": at(b + 9)})
        return Answer(at(mb.STATUS), at(mb.ECHO_SEQ), at(mb.ACTIVE_SEQ), at(mb.ERROR_CODE), at(mb.ERROR_TEXT),
                      at(mb.RESULT_COMMAND), at(mb.PICKS_REPORTED), at(mb.PICKS_FOUND), at(mb.VERIFY_PASSED),
                      at(mb.REFUSED_SEQ), i32(mb.DRIFT_PX) / 1000, i32(mb.DRIFT_MM) / 1000, i32(mb.LATENCY) / 10,
                      picks)


def plc(cell: PlcApp | PlcCell) -> ModbusTcpClient:
    client = ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=5, retries=0)
    assert client.connect()
    return client


def read_answer(client: ModbusTcpClient) -> Answer:
    r = client.read_holding_registers(mb.STATUS, count=100, device_id=UNIT)
    assert not r.isError(), r
    return Answer.parse(list(r.registers))


def wait_answer(client: ModbusTcpClient, seq: int, timeout_s: float = 60.0) -> Answer:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        a = read_answer(client)
        if a.echo == seq:
            return a
        time.sleep(0.01)
    raise AssertionError(f"no answer to request {seq} within {timeout_s} s")


def message(client: ModbusTcpClient) -> str:
    r = client.read_holding_registers(mb.MESSAGE, count=mb.MESSAGE_REGS, device_id=UNIT)
    return mb.words_ascii(list(r.registers))


def request(client: ModbusTcpClient, command: int, recipe: int, seq: int) -> None:
    r = client.write_registers(mb.COMMAND, [command, recipe, seq], device_id=UNIT)
    assert not r.isError(), r


def test_register_encodings_round_trip() -> None:
    for v in (0, 1, -1, 58000, -123456, 2**31 - 1, -(2**31)):
        words = mb.int32_words(v)
        assert all(0 <= w <= 0xFFFF for w in words)
        assert mb.words_int32(words) == v
    assert mb.int32_words(-1) == [0xFFFF, 0xFFFF]
    assert mb.int32_words(0x12345678) == [0x1234, 0x5678]  # high word first
    assert mb.int32_words(1e12) == [0x7FFF, 0xFFFF] and mb.int32_words(math.nan) == [0, 0]
    assert mb.words_ascii(mb.ascii_words("recipe 9 not found")) == "recipe 9 not found"
    assert len(mb.ascii_words("x" * 500)) == mb.MESSAGE_REGS


def test_plc_picks_and_reads_the_pose_against_truth(plc_app: PlcApp) -> None:
    with plc(plc_app) as client:
        seq = next_seq()
        request(client, mb.CMD_PICK, RECIPE, seq)
        # Once the write is answered the request is running: BUSY, and DONE/ERROR are clear.
        first = read_answer(client)
        assert first.active == seq
        assert first.echo == seq or (first.status & mb.BUSY and not first.status & (mb.DONE | mb.ERROR))
        a = wait_answer(client, seq)
    assert a.status == mb.DONE, (a, message(client))
    assert a.error_code == 0 and a.error_text == 0 and a.command == mb.CMD_PICK
    assert a.reported >= 1 and a.found >= a.reported
    best = a.picks[0]
    assert math.hypot(best["x_mm"] - plc_app.part_x_mm, best["y_mm"] - plc_app.part_y_mm) < 0.5
    assert abs(best["z_mm"] - 5.0) < 0.011  # the recipe's grasp height above the table
    assert abs(best["yaw_deg"]) <= 90.0 and best["reachable"] == 1 and best["score"] >= 0.6
    assert a.latency_ms > 0


def test_plc_verifies_the_calibration(plc_app: PlcApp) -> None:
    with plc(plc_app) as client:
        seq = next_seq()
        request(client, mb.CMD_VERIFY, 0, seq)
        a = wait_answer(client, seq)
    assert a.status == mb.DONE and a.command == mb.CMD_VERIFY and a.verify_passed == 1
    assert 0 <= a.drift_px < 1.0 and 0 <= a.drift_mm < 0.5
    assert a.reported == 0


def test_plc_that_writes_garbage_gets_errors_never_a_dead_server(plc_app: PlcApp) -> None:
    with plc(plc_app) as client:
        seq = next_seq()
        request(client, 99, RECIPE, seq)  # no such command: answered at once
        a = read_answer(client)
        assert a.echo == seq and a.status == mb.ERROR
        assert (a.error_code, a.error_text) == (CLASS_REQUEST, TEXT_UNKNOWN_COMMAND)
        assert "unknown command code 99" in message(client)

        seq = next_seq()
        request(client, mb.CMD_PICK, 65000, seq)  # no such recipe
        a = wait_answer(client, seq)
        assert a.status == mb.ERROR and (a.error_code, a.error_text) == (CLASS_SETUP, TEXT_UNKNOWN_RECIPE)
        assert "65000" in message(client) and a.reported == 0

        # Writing the same sequence again starts nothing; sequence 0 is never a request.
        request(client, mb.CMD_IDLE, 0, seq)
        request(client, mb.CMD_IDLE, 0, 0)
        assert read_answer(client).echo == seq and read_answer(client).status == mb.ERROR

        # Protocol-level garbage: refused with Modbus exceptions, nothing changes.
        for r in (client.write_register(mb.ECHO_SEQ, 5, device_id=UNIT),  # read-only block
                  client.write_register(5, 1, device_id=UNIT),  # unmapped address
                  client.read_holding_registers(mb.END - 4, count=10, device_id=UNIT),  # past the map
                  client.read_coils(0, count=8, device_id=UNIT)):  # not a register function
            assert isinstance(r, ExceptionResponse), r
        assert client.write_register(mb.ECHO_SEQ, 5, device_id=UNIT).exception_code == 2
        assert client.read_coils(0, count=8, device_id=UNIT).exception_code == 1
        assert read_answer(client).echo == seq

    # Bytes that are not Modbus at all, then a half frame and a hang-up.
    for junk in (b"\xde\xad\xbe\xef" * 64, b"GET / HTTP/1.1\r\n\r\n", b"\x00\x01\x00\x00\x00\x06\x01\x03"):
        with socket.create_connection(("127.0.0.1", plc_app.modbus_port), timeout=5) as s:
            s.sendall(junk)
            time.sleep(0.05)
    with plc(plc_app) as client:
        seq = next_seq()
        request(client, mb.CMD_IDLE, 0, seq)  # the no-op request: answered at once
        a = read_answer(client)
        assert a.echo == seq and a.status == mb.DONE and a.error_code == 0 and message(client) == ""


def test_plc_that_disconnects_mid_handshake_reads_the_result_after_reconnecting(plc_app: PlcApp) -> None:
    seq = next_seq()
    client = plc(plc_app)
    request(client, mb.CMD_PICK, RECIPE, seq)
    client.close()  # gone before the answer

    # Meanwhile another PLC connection writes a new request: refused while busy, flagged, not applied.
    with plc(plc_app) as other:
        busy = read_answer(other)
        assert busy.status & mb.BUSY and busy.active == seq
        r = other.write_registers(mb.COMMAND, [mb.CMD_PICK, RECIPE, seq + 1000], device_id=UNIT)
        assert isinstance(r, ExceptionResponse) and r.exception_code == 6  # device busy
        refused = read_answer(other)
        assert refused.status & mb.REFUSED and refused.refused_seq == seq + 1000 and refused.active == seq
        seq_reg = other.read_holding_registers(mb.SEQUENCE, count=1, device_id=UNIT).registers[0]
        assert seq_reg == seq

    with plc(plc_app) as again:  # the PLC is back
        a = wait_answer(again, seq)
        assert a.status & mb.DONE and not a.status & mb.BUSY and a.reported >= 1
        assert math.hypot(a.picks[0]["x_mm"] - plc_app.part_x_mm, a.picks[0]["y_mm"] - plc_app.part_y_mm) < 0.5
        assert a.status & mb.REFUSED  # kept until the next accepted request
        seq2 = next_seq() + 1000
        request(again, mb.CMD_IDLE, 0, seq2)
        a2 = read_answer(again)
        assert a2.echo == seq2 and a2.status == mb.DONE  # REFUSED cleared


def test_other_unit_ids_are_answered_gateway_no_response(plc_app: PlcApp) -> None:
    with plc(plc_app) as client:
        r = client.read_holding_registers(mb.STATUS, count=1, device_id=UNIT + 1)
        assert isinstance(r, ExceptionResponse) and r.exception_code == 0x0B
        assert not read_answer(client).status & 0xFFF0  # still serving unit 1
