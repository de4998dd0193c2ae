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


# -- the struct-level fast path (cellctl.plc.enip_fast) against cpppo, frame by frame -------------------------------


def _recv_frame(s: socket.socket) -> bytes | None:
    """One encapsulation frame from the server, or None when it closed the connection."""
    buf = b""
    try:
        while len(buf) < 24 or len(buf) < 24 + struct.unpack_from("<H", buf, 2)[0]:
            chunk = s.recv(4096)
            if not chunk:
                return None
            buf += chunk
    except (ConnectionResetError, TimeoutError):
        return None
    return buf


def _path(name: str, element: int | None = None, wide: bool = False) -> bytes:
    raw = name.encode()
    p = bytes([0x91, len(raw)]) + raw + b"\0" * (len(raw) % 2)
    if element is not None:
        p += struct.pack("<BBH", 0x29, 0, element) if wide else bytes([0x28, element])
    return p


def _cip(service: int, path: bytes, data: bytes) -> bytes:
    return bytes([service, len(path) // 2]) + path + data


def _read(name: str, count: int = 1, element: int | None = None, wide: bool = False) -> bytes:
    return _cip(0x4C, _path(name, element, wide), struct.pack("<H", count))


def _write(name: str, type_code: int, value: bytes, count: int = 1) -> bytes:
    return _cip(0x4D, _path(name), struct.pack("<HH", type_code, count) + value)


class _Session:
    """A raw EtherNet/IP client as pylogix talks: Register Session, Large Forward Open, then frames."""

    def __init__(self, port: int) -> None:
        self.s = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.s.sendall(_register_session())
        reply = _recv_frame(self.s)
        assert reply is not None
        self.session = struct.unpack_from("<I", reply, 4)[0]
        # pylogix's Large Forward Open (0x5B) to the Connection Manager, 4002-byte connections, backplane slot 0
        forward_open = bytes.fromhex("5b 02 20 06 24 01 0a 0e 02 00 00 20 ed 5d 00 00 91 95 37 13 2a 00 00 00"
                                     "03 00 00 00 34 12 20 00 a2 0f 00 42 01 40 20 00 a2 0f 00 42 a3 03 01 00"
                                     "20 02 24 01")
        reply = self.ask(self.rr(forward_open))
        assert reply is not None and reply[40] == 0xDB and reply[42] == 0, reply
        self.conn = struct.unpack_from("<I", reply, 44)[0]

    def ask(self, frame: bytes) -> bytes | None:
        self.s.sendall(frame)
        return _recv_frame(self.s)

    def unit(self, cip: bytes, session: int | None = None, conn: int | None = None, extra: int = 0,
             seq: int = 9) -> bytes:
        conn = self.conn if conn is None else conn
        body = struct.pack("<IHHHHIHHH", 0, 0, 2, 0xA1, 4, conn, 0xB1, len(cip) + 2 + extra, seq) + cip
        return self.encap(0x70, body, session)

    def rr(self, cip: bytes, session: int | None = None, timeout: int = 0) -> bytes:
        body = struct.pack("<IHHHHHH", 0, timeout, 2, 0, 0, 0xB2, len(cip)) + cip
        return self.encap(0x6F, body, session)

    def encap(self, command: int, body: bytes, session: int | None = None) -> bytes:
        return struct.pack("<HHII8sI", command, len(body), self.session if session is None else session, 0,
                           b"cellctl!", 0) + body

    def close(self) -> None:
        self.s.close()


def _unconnected_send(cip: bytes, slot: int = 0) -> bytes:
    return (bytes([0x52, 2, 0x20, 6, 0x24, 1, 10, 0xFF]) + struct.pack("<H", len(cip)) + cip
            + b"\0" * (len(cip) % 2) + bytes([1, 0, 1, slot]))


# (name, frame builder, whether the fast path answers it): every one answered exactly as cpppo answers it.
PROBES: list[tuple[str, Any, bool]] = [
    ("read DINT", lambda c: c.unit(_read("CC_EchoSeq")), True),
    ("read REAL[64]", lambda c: c.unit(_read("CC_Picks", 64)), True),
    ("read REAL[3..4]", lambda c: c.unit(_read("CC_Picks", 2, element=3)), True),
    ("read REAL[60..63], 16-bit element", lambda c: c.unit(_read("CC_Picks", 4, element=60, wide=True)), True),
    ("read DINT[7]", lambda c: c.unit(_read("CC_Counters", 7)), True),
    ("read scalar [0]", lambda c: c.unit(_read("CC_Command", 1, element=0)), True),
    ("read STRING", lambda c: c.unit(_read("CC_Message")), True),
    ("read, unconnected", lambda c: c.rr(_read("CC_ErrorText")), True),
    ("read, unconnected, a timeout", lambda c: c.rr(_read("CC_ErrorText"), timeout=5), True),
    ("read, Unconnected Send to slot 0", lambda c: c.rr(_unconnected_send(_read("CC_PicksReported"))), True),
    ("write DINT", lambda c: c.unit(_write("CC_Count", 0xC4, struct.pack("<i", 0))), True),
    ("write a read-only tag", lambda c: c.unit(_write("CC_Status", 0xC4, struct.pack("<i", 7))), False),
    ("write a REAL into a DINT", lambda c: c.unit(_write("CC_Count", 0xCA, struct.pack("<f", 1.5))), False),
    ("write a SINT into a DINT", lambda c: c.unit(_write("CC_Count", 0xC2, b"\0")), False),
    ("write two DINTs into one", lambda c: c.unit(_write("CC_Count", 0xC4, b"\0" * 8, count=2)), False),
    ("read an unknown tag", lambda c: c.unit(_read("NoSuchTag")), False),
    ("read past the end", lambda c: c.unit(_read("CC_Picks", 65)), False),
    ("read two of a scalar", lambda c: c.unit(_read("CC_EchoSeq", 2)), False),
    ("read zero elements", lambda c: c.unit(_read("CC_EchoSeq", 0)), False),
    ("read with a trailing byte", lambda c: c.unit(_read("CC_EchoSeq") + b"\0"), False),
    ("read, a path longer than the request", lambda c: c.unit(bytes([0x4C, 40]) + _path("CC_EchoSeq")), False),
    ("Read Tag Fragmented", lambda c: c.unit(_cip(0x52, _path("CC_Picks"), struct.pack("<HI", 64, 0))), False),
    ("Unconnected Send to slot 3", lambda c: c.rr(_unconnected_send(_read("CC_PicksReported"), slot=3)), False),
    ("an unknown connection id", lambda c: c.unit(_read("CC_EchoSeq"), conn=c.conn ^ 0xFFFF), False),
    ("another session's handle", lambda c: c.unit(_read("CC_EchoSeq"), session=c.session ^ 1), False),
    ("a data item longer than the frame", lambda c: c.unit(_read("CC_EchoSeq"), extra=4), False),
    ("a data item shorter than the frame", lambda c: c.unit(_read("CC_EchoSeq"), extra=-4), False),
    ("a truncated request", lambda c: c.unit(_read("CC_EchoSeq")[:3]), False),
]


def _normal(reply: bytes | None, c: _Session) -> bytes | None:
    """The reply with this connection's session handle and connection id blanked (cpppo draws them)."""
    if reply is None:
        return None
    out = bytearray(reply)
    if struct.unpack_from("<I", out, 4)[0] in (c.session, c.session ^ 1):
        out[4:8] = b"\0" * 4
    if out[0] == 0x70 and len(out) >= 40 and struct.unpack_from("<I", out, 36)[0] in (c.conn, c.conn ^ 0xFFFF):
        out[36:40] = b"\0" * 4
    return bytes(out)


def _answers(port: int) -> dict[str, bytes | None]:
    """Each probe's reply (None: the connection was closed), on one connection until one is closed."""
    out: dict[str, bytes | None] = {}
    c: _Session | None = None
    try:
        for name, build, _fast in PROBES:
            c = c or _Session(port)
            out[name] = _normal(c.ask(build(c)), c)
            if out[name] is None:
                c.close()
                c = None
    finally:
        if c is not None:
            c.close()
    return out


def test_the_fast_path_answers_as_cpppo_does_and_declines_everything_else(
        cell: PlcApp, monkeypatch: pytest.MonkeyPatch) -> None:
    from cellctl.plc.enip_fast import FastPath

    answered: list[bytes] = []
    original = FastPath.answer

    def spy(self: FastPath, frame: bytes) -> bytes | None:
        reply = original(self, frame)
        if reply is not None:
            answered.append(frame)
        return reply

    monkeypatch.setattr(FastPath, "answer", spy)
    monkeypatch.setattr(FastPath, "enabled", False)
    by_cpppo = _answers(cell.enip_port)
    assert not answered
    monkeypatch.setattr(FastPath, "enabled", True)
    fast = _answers(cell.enip_port)
    for name, _build, _takes in PROBES:
        assert fast[name] == by_cpppo[name], (name, fast[name], by_cpppo[name])
    taken = [name for name, _b, takes in PROBES if takes]
    assert len(answered) == len(taken), answered  # exactly the well-formed reads and writes of our tags
    assert by_cpppo["read DINT"] is not None and by_cpppo["read DINT"][48] == 0  # a real answer, status 0
    assert by_cpppo["read an unknown tag"] is not None and by_cpppo["read an unknown tag"][48] == 0x05
    # A Logix client's handshake runs on the fast path: only session and connection set-up reach cpppo.
    answered.clear()
    with logix(cell.enip_port) as c:
        assert request(c, 0)["status"] & DONE
    assert len(answered) >= 10, len(answered)
