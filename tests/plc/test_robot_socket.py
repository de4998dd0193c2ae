"""The robot socket of the virtual cell, driven by a plain TCP client as a robot program would: PICK in KUKA's
A-B-C convention (checked against the pick's own rotation), VERIFY, STATUS, errors; and hostile input on
every front end (over-long and binary lines, a silent client, 50 connections at once, Modbus garbage):
each answered with an error or a closed connection, the other front ends and REST unaffected, the robot
never moved."""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from calibration import geometry as g
from cellctl.plc import modbus_server as mb
from cellctl.plc.requests import TEXT_BUSY, TEXT_UNKNOWN_COMMAND, TEXT_UNKNOWN_RECIPE
from tests.support.served_plc import RECIPE, PlcApp, in_process_plc

IDLE_S = 1.5


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PlcApp]:
    with in_process_plc(tmp_path_factory.mktemp("socket"), all_front_ends=True,
                        robot_socket={"pose_format": "kuka", "idle_timeout_s": IDLE_S}) as c:
        yield c


def connect(cell: PlcApp) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", cell.robot_socket_port), timeout=60)
    s.settimeout(60)
    return s


def ask(s: socket.socket, line: bytes) -> str:
    s.sendall(line)
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(4096)
        if not chunk:
            break
        buf += chunk
    return buf.decode("ascii").strip()


def closed(s: socket.socket, timeout_s: float = 10.0) -> bool:
    """Whether the server closed the connection (reads what is left first)."""
    s.settimeout(timeout_s)
    try:
        while s.recv(4096):
            pass
        return True
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def robot_pose(cell: PlcApp) -> dict[str, float]:
    r = cell.http().get("/robots/robot0/state")
    assert r.status_code == 200, r.text
    pose: dict[str, float] = r.json()["pose_ur"]
    return pose


def test_pick_answers_the_best_reachable_pick_in_kuka_abc(cell: PlcApp) -> None:
    with connect(cell) as s:
        line = ask(s, f"PICK {RECIPE}\r\n".encode())
    words = line.split()
    assert words[0] == "OK" and len(words) == 10, line  # OK n x y z A B C score sigma
    n, x, y, z, a, b, c, score, sigma = (float(w) for w in words[1:])
    assert n >= 1 and abs(x - cell.part_x_mm) < 1.0 and abs(y - cell.part_y_mm) < 1.0, line
    assert 0.5 < score <= 1.0 and 0 < sigma < 1.0
    # The same pick over REST: its rotation (UR rotation vector of T_base_tool) is the one A B C describe.
    rest = cell.http().post("/pick", json={"recipe_id": RECIPE}).json()
    best = next(p for p in rest["picks"] if p["reachable"])
    q = best["pick_pose"]
    R_rest = g.rotvec_to_matrix([q["rx_rad"], q["ry_rad"], q["rz_rad"]])
    R_socket = g.zyx_deg_to_matrix(a, b, c)  # KUKA: Rz(A) Ry(B) Rx(C)
    assert np.degrees(g.rotation_angle(R_rest.T @ R_socket)) < 0.5, (line, q)
    assert R_socket[2, 2] < -0.99  # the tool points down


def test_verify_status_and_errors(cell: PlcApp) -> None:
    with connect(cell) as s:
        verify = ask(s, b"VERIFY\n").split()
        assert verify[0] == "OK" and float(verify[1]) < 1.0, verify  # drift in px on the true calibration
        assert ask(s, b"STATUS\n") == "OK 0 0 0"  # not latched, not busy, no run
        assert ask(s, b"status\r\n") == "OK 0 0 0"
        assert ask(s, b"PICK 77\n").startswith(f"ERR {TEXT_UNKNOWN_RECIPE} ")
        assert ask(s, b"PICK\n").startswith(f"ERR {TEXT_UNKNOWN_COMMAND} ")
        assert ask(s, b"PICK one\n").startswith("ERR ")
        assert ask(s, b"MOVE 1 2 3\n").startswith(f"ERR {TEXT_UNKNOWN_COMMAND} unknown request")
        assert ask(s, b"\n").startswith(f"ERR {TEXT_UNKNOWN_COMMAND} ")
        assert ask(s, b"\x00\xff\xfe\x80binary\n").startswith(f"ERR {TEXT_UNKNOWN_COMMAND} not an ASCII line")
        assert ask(s, b"STATUS\n") == "OK 0 0 0"  # the connection still serves
    status = cell.http().get("/plc/status").json()["front_ends"]["robot_socket"]
    assert status["enabled"] and status["last_request"]["kind"] == "pick" and status["requests"] >= 3


def test_an_over_long_line_is_refused_and_closed(cell: PlcApp) -> None:
    with connect(cell) as s:
        answer = ask(s, b"PICK " + b"1" * 300 + b"\n")
        assert answer.startswith(f"ERR {TEXT_UNKNOWN_COMMAND} line longer than 256 bytes"), answer
        assert closed(s)
    with connect(cell) as s:  # 300 bytes without an end of line at all
        s.sendall(b"A" * 300)
        assert ask(s, b"").startswith(f"ERR {TEXT_UNKNOWN_COMMAND} ")
        assert closed(s)


def test_a_silent_client_is_closed(cell: PlcApp) -> None:
    with connect(cell) as s:
        t0 = time.monotonic()
        assert closed(s, timeout_s=IDLE_S + 10)
        assert IDLE_S - 0.2 <= time.monotonic() - t0 < IDLE_S + 5


def test_fifty_connections_at_once_leave_the_other_front_ends_and_rest_unaffected(
        cell: PlcApp, caplog: pytest.LogCaptureFixture) -> None:
    before = robot_pose(cell)
    caplog.set_level(logging.WARNING)
    socks = [socket.create_connection(("127.0.0.1", cell.robot_socket_port), timeout=10) for _ in range(50)]
    # The Modbus and EtherNet/IP floods come from another address (127.0.0.2) than the PLC (127.0.0.1), as on a
    # plant network: the per-address cap keeps the PLC's own connection possible.
    modbus_socks = [socket.create_connection(("127.0.0.1", cell.modbus_port), timeout=10,
                                             source_address=("127.0.0.2", 0)) for _ in range(50)]
    enip_socks = [socket.create_connection(("127.0.0.1", cell.enip_port), timeout=10,
                                           source_address=("127.0.0.2", 0)) for _ in range(50)]
    try:
        time.sleep(0.3)
        refused = []
        for s in socks:
            s.settimeout(0.01)
            try:
                data = s.recv(200)
            except TimeoutError:
                data = b"(kept)"
            refused.append(data)
        assert sum(1 for d in refused if d.startswith(f"ERR {TEXT_BUSY} too many clients".encode())) == 46, refused
        kept = [s for s, d in zip(socks, refused, strict=True) if d == b"(kept)"]
        assert len(kept) == 4
        kept[0].settimeout(60)
        assert ask(kept[0], b"STATUS\n") == "OK 0 0 0"  # the four admitted clients are served
        # Modbus closes the connections over its per-address cap; the PLC's own client still gets through,
        # a request runs, REST answers and Stop would: nothing waits on the flood.
        assert sum(1 for s in modbus_socks if closed(s, timeout_s=0.05)) >= 50 - 16  # over the per-address cap
        with ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=10, retries=0) as plc:
            r = plc.read_holding_registers(mb.STATUS, count=10, device_id=1)
            assert not r.isError(), r
            assert not plc.write_registers(mb.COMMAND, [1, RECIPE, 9100], device_id=1).isError()
            deadline = time.monotonic() + 60
            while plc.read_holding_registers(mb.ECHO_SEQ, count=1, device_id=1).registers[0] != 9100:
                assert time.monotonic() < deadline
                time.sleep(0.02)
            assert plc.read_holding_registers(mb.STATUS, count=1, device_id=1).registers[0] & mb.DONE
        t0 = time.monotonic()
        assert cell.http().get("/health").status_code == 200
        assert cell.http().get("/plc/status").status_code == 200
        assert time.monotonic() - t0 < 5.0
    finally:
        for s in socks + modbus_socks + enip_socks:
            s.close()
    assert robot_pose(cell) == pytest.approx(before, abs=1e-9)  # the robot never moved
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


def test_hostile_modbus_input_is_answered_or_closed_without_a_traceback(
        cell: PlcApp, caplog: pytest.LogCaptureFixture) -> None:
    before = robot_pose(cell)
    caplog.set_level(logging.INFO)
    # Every undocumented function code: exception 01 (illegal function).
    pdus = {1: "00000001", 2: "00000001", 5: "0000ff00", 7: "", 8: "00000000", 11: "", 12: "", 15: "0000000101" "01",
            17: "", 20: "0706000100000001", 21: "0906000100000001" "0000", 22: "0000ffff0000",
            23: "00000001000000010200" "00", 24: "0000", 43: "0e0100", 0x41: "0000", 0x64: ""}
    for fc, data in pdus.items():
        with socket.create_connection(("127.0.0.1", cell.modbus_port), timeout=5) as s:
            body = bytes([1, fc]) + bytes.fromhex(data)
            s.sendall(bytes([0, 7, 0, 0, 0, len(body)]) + body)
            s.settimeout(5)
            reply = s.recv(256)
            # exception 01 (illegal function); a request pymodbus cannot even decode is answered 0x80 + 01
            assert reply[7] in (fc | 0x80, 0x80) and reply[8] == 1, (fc, reply)
    # Random frames: closed connections, no traceback; the log stays small.
    rng = np.random.default_rng(34)
    for _ in range(200):
        with socket.create_connection(("127.0.0.1", cell.modbus_port), timeout=5) as s:
            s.sendall(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
    # The server still serves (a PLC reconnects while the closed garbage connections are being let go).
    deadline = time.monotonic() + 10
    while True:
        try:
            with ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=10, retries=0) as plc:
                assert not plc.read_holding_registers(mb.STATUS, count=100, device_id=1).isError()
            break
        except ConnectionError:
            assert time.monotonic() < deadline
            time.sleep(0.2)
    # Every garbage connection was let go (none is counted against the caps any more).
    deadline = time.monotonic() + 10
    while cell.http().get("/plc/status").json()["front_ends"]["modbus"]["clients"] != 0:
        assert time.monotonic() < deadline, cell.http().get("/plc/status").json()["front_ends"]["modbus"]
        time.sleep(0.1)
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    plc_lines = [r for r in caplog.records if r.name.startswith(("pymodbus", "cellctl.plc"))]
    assert len(plc_lines) < 60, [r.getMessage() for r in plc_lines][:80]
    assert robot_pose(cell) == pytest.approx(before, abs=1e-9)


def test_idle_modbus_connections_are_closed(tmp_path_factory: pytest.TempPathFactory) -> None:
    from cellctl.config_listeners import ModbusServerConfig
    from cellctl.plc.modbus_server import ModbusPlcServer
    from tests.support.served import free_port

    port = free_port()
    cfg = ModbusServerConfig(enabled=True, port=port, idle_timeout_s=3.0, max_connections_per_address=3)
    server = _services_server(tmp_path_factory, ModbusPlcServer, cfg)
    try:
        t0 = time.monotonic()
        socks = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(5)]
        assert all(closed(s, timeout_s=1.0) for s in socks[3:])  # over the per-address cap: closed at once
        assert not any(closed(s, timeout_s=0.1) for s in socks[:3])
        assert all(closed(s, timeout_s=10) for s in socks[:3])  # silent: closed after the idle timeout
        assert 2.5 < time.monotonic() - t0 < 9
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0) as plc:
            assert not plc.read_holding_registers(mb.STATUS, count=10, device_id=1).isError()
        assert server.closed_idle >= 3 and server.closed_over_cap >= 2
    finally:
        for s in socks:
            s.close()
        server.stop()
        server.services.close()


def _services_server(tmp_path_factory: pytest.TempPathFactory, cls: type, cfg: object) -> mb.ModbusPlcServer:
    """A Modbus server on a cell whose devices are not opened (the connection rules need no pick)."""
    import yaml

    from cellctl.cell import Cell
    from cellctl.config import default_config_text, parse_config
    from cellctl.jobs import JobManager
    from cellctl.services import Services
    from cellctl.store import open_store

    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path_factory.mktemp("modbus-idle") / "cell.db")}
    config = parse_config(data)
    services = Services(config, Cell(config), open_store(config), JobManager())
    server: mb.ModbusPlcServer = cls(services, "127.0.0.1", cfg.port, 1, config=cfg)  # type: ignore[attr-defined]
    return server.start()


def test_a_request_from_one_front_end_while_another_runs_is_refused_busy(cell: PlcApp) -> None:
    """One request at a time for the cell: a socket PICK during a Modbus verify is answered ERR 2 at once."""
    with ModbusTcpClient("127.0.0.1", port=cell.modbus_port, timeout=10, retries=0) as plc:
        assert not plc.write_registers(mb.COMMAND, [2, 0, 9001], device_id=1).isError()  # verify (~1 s)
        with connect(cell) as s:
            answers = [ask(s, f"PICK {RECIPE}\n".encode())]
        deadline = time.monotonic() + 60
        while plc.read_holding_registers(mb.ECHO_SEQ, count=1, device_id=1).registers[0] != 9001:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    assert answers[0].startswith(f"ERR {TEXT_BUSY} refused: a verify request from the modbus front end"), answers
