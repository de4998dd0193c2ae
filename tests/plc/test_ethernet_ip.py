"""The EtherNet/IP tag server of the virtual cell, driven by pylogix (a Rockwell Logix client the project did
not write) as the PLC: write the request tags, poll CC_EchoSeq, read the picks; hostile CIP input."""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from pylogix import PLC

from cellctl.plc.enip_tags import BUSY, DONE, ERROR, PICK_FIELDS, REFUSED
from cellctl.plc.production import ENDED, STATES
from cellctl.plc.requests import CLASS_REQUEST, TEXT_UNKNOWN_COMMAND, TEXT_UNKNOWN_RECIPE
from tests.support.served_plc import RECIPE, PlcApp, in_process_plc

_seq = [500]


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PlcApp]:
    with in_process_plc(tmp_path_factory.mktemp("enip"), all_front_ends=True) as c:
        yield c


def next_seq() -> int:
    _seq[0] += 1
    return _seq[0]


def logix(port: int) -> PLC:
    c = PLC()
    c.IPAddress = "127.0.0.1"
    c.Port = port
    c.SocketTimeout = 10.0
    return c


def ok(response: Any) -> Any:
    assert response.Status == "Success", response
    return response.Value


def request(c: PLC, command: int, recipe: int = 0, count: int = 0, timeout_s: float = 60.0) -> dict[str, Any]:
    """The handshake as a PLC program runs it: the request tags, then a new sequence; poll CC_EchoSeq."""
    seq = next_seq()
    ok(c.Write("CC_Command", command))
    ok(c.Write("CC_Recipe", recipe))
    ok(c.Write("CC_Count", count))
    ok(c.Write("CC_Sequence", seq))
    deadline = time.monotonic() + timeout_s
    while ok(c.Read("CC_EchoSeq")) != seq:
        assert time.monotonic() < deadline, "no answer"
        time.sleep(0.01)
    return answer(c)


def answer(c: PLC) -> dict[str, Any]:
    picks_flat = ok(c.Read("CC_Picks", 64))
    n = ok(c.Read("CC_PicksReported"))
    width = len(PICK_FIELDS)
    picks = [dict(zip(PICK_FIELDS, picks_flat[k * width : (k + 1) * width], strict=True)) for k in range(n)]
    return {"status": ok(c.Read("CC_Status")), "echo": ok(c.Read("CC_EchoSeq")),
            "error_code": ok(c.Read("CC_ErrorCode")), "error_text": ok(c.Read("CC_ErrorText")),
            "message": ok(c.Read("CC_Message")), "picks": picks}


def test_a_logix_client_picks_through_the_tags(cell: PlcApp) -> None:
    with logix(cell.enip_port) as c:
        a = request(c, 1, RECIPE)
        assert a["status"] & DONE and not a["status"] & (BUSY | ERROR), a
        assert a["error_code"] == 0 and a["message"] == ""
        assert len(a["picks"]) >= 1
        best = a["picks"][0]
        # The true part position in the robot base frame (the virtual cell's truth), to a millimetre.
        assert abs(best["x_mm"] - cell.part_x_mm) < 1.0 and abs(best["y_mm"] - cell.part_y_mm) < 1.0, best
        assert 0.5 < best["score"] <= 1.0 and best["reachable"] == 1.0
        assert 0 < best["sigma_mm"] < 1.0, best  # the calibration's uncertainty carried to the pick
        beat = ok(c.Read("CC_Heartbeat"))
        time.sleep(0.25)
        assert ok(c.Read("CC_Heartbeat")) >= beat + 2  # counts every 100 ms
        # The answer stays until the next request: a second client (a PLC after a reconnect) reads it.
    with logix(cell.enip_port) as again:
        assert ok(again.Read("CC_EchoSeq")) == a["echo"] and answer(again)["picks"] == a["picks"]
    status = cell.http().get("/plc/status").json()["front_ends"]["ethernet_ip"]
    assert status["enabled"] and status["last_request"]["kind"] == "pick"
    assert status["last_answer"]["ok"] and status["last_answer"]["picks"] == len(a["picks"])


def test_errors_come_back_in_the_tags(cell: PlcApp) -> None:
    with logix(cell.enip_port) as c:
        a = request(c, 1, 77)
        assert a["status"] & ERROR and a["error_text"] == TEXT_UNKNOWN_RECIPE and "77" in a["message"], a
        b = request(c, 42)
        assert b["error_code"] == CLASS_REQUEST and b["error_text"] == TEXT_UNKNOWN_COMMAND, b
        idle = request(c, 0)
        assert idle["status"] & DONE and idle["picks"] == []


def test_writing_the_same_sequence_again_starts_nothing_and_busy_refuses(cell: PlcApp) -> None:
    with logix(cell.enip_port) as c:
        first = request(c, 0)
        requests = cell.http().get("/plc/status").json()["front_ends"]["ethernet_ip"]["requests"]
        ok(c.Write("CC_Sequence", first["echo"]))  # the same sequence: nothing starts
        assert cell.http().get("/plc/status").json()["front_ends"]["ethernet_ip"]["requests"] == requests
        # A pick, and while it runs a new sequence: the write fails and REFUSED is set.
        seq = next_seq()
        ok(c.Write("CC_Command", 1))
        ok(c.Write("CC_Recipe", RECIPE))
        ok(c.Write("CC_Sequence", seq))
        refused = c.Write("CC_Sequence", seq + 1)
        if ok(c.Read("CC_EchoSeq")) != seq:  # still running when the second write came
            assert refused.Status != "Success" and ok(c.Read("CC_Status")) & REFUSED
        deadline = time.monotonic() + 60
        while ok(c.Read("CC_EchoSeq")) != seq:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert ok(c.Read("CC_Status")) & DONE


def test_unknown_tags_and_read_only_tags_are_refused_and_the_server_goes_on(cell: PlcApp) -> None:
    with logix(cell.enip_port) as c:
        assert c.Read("NoSuchTag").Status != "Success"
        assert c.Write("CC_Status", 7).Status != "Success"  # written by the cell only
        assert c.Write("CC_Picks[3]", 1.5).Status != "Success"
        assert ok(c.Read("CC_Status")) & 0x7 != BUSY  # no request started
        assert request(c, 0)["status"] & DONE


def _register_session() -> bytes:
    return struct.pack("<HHII8sI", 0x65, 4, 0, 0, b"\0" * 8, 0) + struct.pack("<HH", 1, 0)


def test_malformed_cip_packets_close_only_their_connection(cell: PlcApp) -> None:
    before = cell.http().get("/plc/status").json()["front_ends"]["ethernet_ip"]["requests"]
    garbage = [
        b"\xff" * 24 + b"\x00" * 16,  # an unknown encapsulation command
        struct.pack("<HHII8sI", 0x6F, 40, 0xDEAD, 0, b"\0" * 8, 0) + b"\x13" * 40,  # SendRRData, nonsense CPF
        struct.pack("<HHII8sI", 0x6F, 60000, 0, 0, b"\0" * 8, 0),  # a frame longer than the server takes
        _register_session()[:10],  # half a header, then the client leaves
        _register_session() + struct.pack("<HHII8sI", 0x70, 8, 1, 0, b"\0" * 8, 0) + b"\x00\x00\xb2\x00\xff\xff\x00",
    ]
    for frame in garbage:
        with socket.create_connection(("127.0.0.1", cell.enip_port), timeout=5) as s:
            s.sendall(frame)
            s.shutdown(socket.SHUT_WR)
            s.settimeout(5)
            try:
                while s.recv(4096):
                    pass  # an error answer, then the close
            except (ConnectionResetError, TimeoutError):
                pass
    with logix(cell.enip_port) as c:
        assert request(c, 1, RECIPE)["status"] & DONE  # the server still serves
    # The other front ends and REST were not disturbed, nothing ran for the garbage.
    status = cell.http().get("/plc/status").json()
    assert status["front_ends"]["ethernet_ip"]["requests"] == before + 1
    assert cell.http().get("/health").json()["status"] in ("ok", "starting")


def test_a_production_run_starts_and_stops_through_ethernet_ip(tmp_path: Path) -> None:
    from tests.support.production_cell import production_config, teach_recipe
    from tests.support.served import free_port, start_served, stop_served

    path = production_config(tmp_path, count=6)
    cfg = yaml.safe_load(path.read_text())
    port = free_port()
    cfg["plc"] = {"ethernet_ip": {"enabled": True, "host": "127.0.0.1", "port": port}, "allow_motion": True}
    path.write_text(yaml.safe_dump(cfg))
    served = start_served(tmp_path, path)
    try:
        teach_recipe(served.client(timeout_s=60))
        with logix(port) as c:
            started = request(c, 4, 1, count=2)
            assert started["status"] & DONE, started
            deadline = time.monotonic() + 120
            while ok(c.Read("CC_EndedBecause")) == 0:
                assert time.monotonic() < deadline
                time.sleep(0.1)
            assert ok(c.Read("CC_EndedBecause")) == ENDED["count_reached"]
            assert ok(c.Read("CC_RunState")) == STATES["complete"]
            counters = ok(c.Read("CC_Counters", 7))
            assert counters[0] == 2 and counters[1] == 2, counters  # picked, placed
            assert request(c, 4, 1, count=0)["status"] & DONE  # until the area is empty ...
            while ok(c.Read("CC_RunState")) != STATES["running"]:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            assert request(c, 7)["status"] & DONE  # ... stopped by the PLC after the cycle in progress
            while ok(c.Read("CC_EndedBecause")) == 0:
                assert time.monotonic() < deadline
                time.sleep(0.1)
            assert ok(c.Read("CC_EndedBecause")) == ENDED["stopped"]
        assert served.client().get("/production").json()["ended_because"] == "stopped"
    finally:
        stop_served(served)
