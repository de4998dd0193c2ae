"""docs/plc-modbus.md against the register map's one table in code (cellctl.plc.modbus_map): every field the
document names is at the address the server serves it, and every field the server serves is documented."""

from __future__ import annotations

import re
from pathlib import Path

from cellctl.plc import modbus_map as mm
from cellctl.plc import modbus_server as mb

DOC = Path(__file__).resolve().parents[2] / "docs" / "plc-modbus.md"
ABSOLUTE = re.compile(r"^\| (\d+)(?:\s*(?:-|\.\.)\s*(\d+))? \| ([A-Z_]+) \|")
OFFSET = re.compile(r"^\| \+(\d+)(?:\s*(?:-|\.\.)\s*\+(\d+))? \| ([A-Z_]+) \|")
REPEATED = re.compile(r"^\| (\d+) \+ (\d+)·k \.\. \+(\d+) \| ([A-Z_]+) \|")


def documented() -> tuple[dict[str, tuple[int, int]], dict[str, tuple[int, int]], dict[str, tuple[int, int, int]]]:
    absolute: dict[str, tuple[int, int]] = {}
    offsets: dict[str, tuple[int, int]] = {}
    repeated: dict[str, tuple[int, int, int]] = {}
    for line in DOC.read_text().splitlines():
        if m := REPEATED.match(line):
            first, stride, extra, name = int(m[1]), int(m[2]), int(m[3]), m[4]
            repeated[name] = (first, stride, first + extra)
        elif m := ABSOLUTE.match(line):
            absolute[m[3]] = (int(m[1]), int(m[2] or m[1]))
        elif m := OFFSET.match(line):
            offsets[m[3]] = (int(m[1]), int(m[2] or m[1]))
    return absolute, offsets, repeated


def test_the_document_names_every_field_at_its_served_address() -> None:
    absolute, offsets, repeated = documented()
    code = {name: (p.address, p.end) for name, p in mm.REGISTERS.items()}
    assert absolute == code
    assert offsets == {name: (p.address, p.end) for name, p in mm.PICK_OFFSETS.items()}
    sigma = {name: (mm.PICK_SIGMA + p.address, mm.SIGMA_STRIDE, mm.PICK_SIGMA + p.end)
             for name, p in mm.SIGMA_OFFSETS.items()}
    assert repeated == sigma
    text = DOC.read_text()
    assert f"**{mm.PICKS} + {mm.PICK_STRIDE}·k**" in text  # where pick k starts
    assert f"(register map version {mm.MAP_VERSION})" in text.splitlines()[0]
    assert f"| {mm.address('MAP_VERSION')} | MAP_VERSION | {mm.MAP_VERSION} (" in text
    sigma_end = mm.SIGMA_END  # version 5 added the slots-in-doubt block after the uncertainty block
    assert f"**{mm.address('SIGMA_SEQ')}..{sigma_end - 1} ({sigma_end - mm.address('SIGMA_SEQ')} registers)**" in text
    assert sigma_end == 236 and mm.address("DOUBT_COUNT") == 236
    assert mm.END == 241 and "241 and above" in text


def test_the_server_and_the_production_block_are_built_from_the_table() -> None:
    served = (mb.STATUS, mb.ECHO_SEQ, mb.PICKED, mb.MESSAGE, mb.PRODUCTION, mb.SIGMA_SEQ, mb.END)
    table = (mm.address("STATUS"), mm.address("ECHO_SEQ"), mm.address("PICKED"), mm.address("MESSAGE"),
             mm.address("RUN_ID"), mm.address("SIGMA_SEQ"), mm.END)
    assert served == table
    values = {"run_id": 7, "state": 1, "ended": 0, "counters": [1, 2, 3, 4, 5, 6, 7], "next_slot": 3,
              "last_result": 1, "last_slot": 2, "cycle_median_ms": 1500, "sigma_mm": 0.06, "sigma_deg": -1}
    words = mm.production_block_words(values)
    assert len(words) == mb.SIGMA_SEQ - mb.PRODUCTION
    at = {name: p.address - mb.PRODUCTION for name, p in mm.PRODUCTION_BLOCK.items()}
    assert mm.words_int32(words[at["RUN_ID"] : at["RUN_ID"] + 2]) == 7
    assert mm.words_int32(words[at["COUNTERS"] + 12 : at["COUNTERS"] + 14]) == 7
    assert mm.words_int32(words[at["LAST_SIGMA_UM"] : at["LAST_SIGMA_UM"] + 2]) == 60
    assert mm.words_int32(words[at["LAST_SIGMA_MDEG"] : at["LAST_SIGMA_MDEG"] + 2]) == -1


def test_the_document_names_every_status_bit_the_server_sets() -> None:
    text = DOC.read_text()
    for name, bit in mm.STATUS_BITS.items():
        assert f"bit {bit} {name}" in text, name
        assert getattr(mb, name) == 1 << bit  # the server's masks come from the table
    assert mb.LIVE_BITS & mb.DRIFT_ALARM  # live on every read, like the robot's bits
