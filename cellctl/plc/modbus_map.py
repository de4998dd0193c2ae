"""The Modbus register map (version 5) as one table: the server's addresses, the production block's
words and docs/plc-modbus.md all come from it (``tests/plc/test_modbus_map_docs.py`` holds the
document to it).

Each block is a run of fields laid out one after the other from the block's start; a field is a
name, a width in registers and who writes it (``W`` the PLC, ``R`` the server). Addresses are
protocol addresses, 0-based. int32 values are two registers, big-endian words (high word first),
two's complement; text is ASCII, two characters per register, high byte first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

MAP_VERSION = 5


@dataclass(frozen=True)
class Field:
    """One register field: its name, width in registers, who writes it and what it holds."""

    name: str
    count: int = 1
    access: Literal["R", "W"] = "R"
    kind: Literal["u16", "int32", "ascii", "int32s"] = "u16"
    """``int32s``: ``count // 2`` int32 values (the production counters)."""


@dataclass(frozen=True)
class Placed:
    """A field at its address."""

    field: Field
    address: int

    @property
    def end(self) -> int:
        """The last register of the field (inclusive)."""
        return self.address + self.field.count - 1


def layout(start: int, fields: Sequence[Field]) -> dict[str, Placed]:
    """The fields placed one after the other from ``start``."""
    out: dict[str, Placed] = {}
    address = start
    for f in fields:
        out[f.name] = Placed(f, address)
        address += f.count
    return out


COMMAND_FIELDS = (Field("COMMAND", access="W"), Field("RECIPE", access="W"), Field("SEQUENCE", access="W"),
                  Field("COUNT", access="W"))
ANSWER_FIELDS = (
    Field("STATUS"), Field("ECHO_SEQ"), Field("ACTIVE_SEQ"), Field("ERROR_CODE"), Field("ERROR_TEXT"),
    Field("RESULT_COMMAND"), Field("PICKS_REPORTED"), Field("PICKS_FOUND"), Field("VERIFY_PASSED"),
    Field("REFUSED_SEQ"), Field("DRIFT_PX", 2, kind="int32"), Field("DRIFT_MM", 2, kind="int32"),
    Field("LATENCY", 2, kind="int32"), Field("HEARTBEAT"), Field("MAX_PICKS"), Field("MAP_VERSION"), Field("PICKED"),
)
PICK_FIELDS = (Field("X", 2, kind="int32"), Field("Y", 2, kind="int32"), Field("Z", 2, kind="int32"),
               Field("ROTATION", 2, kind="int32"), Field("SCORE"), Field("REACHABLE"))
"""One pick's fields, at offsets from the pick's first register (pick k at ``PICKS + PICK_STRIDE * k``)."""
MAX_PICKS = 8
MESSAGE_FIELDS = (Field("MESSAGE", 64, kind="ascii"),)
PRODUCTION_FIELDS = (
    Field("RUN_ID", 2, kind="int32"), Field("RUN_STATE"), Field("ENDED_BECAUSE"), Field("COUNTERS", 14, kind="int32s"),
    Field("NEXT_SLOT", 2, kind="int32"), Field("LAST_RESULT"), Field("LAST_SLOT", 2, kind="int32"),
    Field("CYCLE_MEDIAN_MS", 2, kind="int32"), Field("LAST_SIGMA_UM", 2, kind="int32"),
    Field("LAST_SIGMA_MDEG", 2, kind="int32"),
)
CONVEYOR_FIELDS = (Field("MISSED_WINDOW", 2, kind="int32"), Field("QUEUE_LENGTH"))
"""Production from a belt (docs/conveyor.md), version 5: after the in-doubt block (every older address is
where it was)."""
SIGMA_SEQ_FIELDS = (Field("SIGMA_SEQ"),)
SIGMA_FIELDS = (Field("SIGMA_UM", 2, kind="int32"), Field("SIGMA_MDEG", 2, kind="int32"))
"""One pick's uncertainty, at offsets from ``PICK_SIGMA + SIGMA_STRIDE * k``."""
DOUBT_FIELDS = (Field("DOUBT_COUNT"), Field("DOUBT_RECIPE", 2, kind="int32"), Field("DOUBT_SLOT", 2, kind="int32"))
"""The slots in doubt (version 5): how many, and the first one's recipe and slot (-1: none)."""

STATUS_BITS: dict[str, int] = {"BUSY": 0, "DONE": 1, "ERROR": 2, "REFUSED": 3, "ROBOT_LATCHED": 4, "ROBOT_OWNED": 5,
                               "DRIFT_ALARM": 6}
"""STATUS (register 10) bit numbers; bits 4-6 are live on every read. DRIFT_ALARM: the last drift check of the
cell's fixed camera raised an alarm (docs/drift.md)."""

COMMAND_BLOCK = layout(0, COMMAND_FIELDS)
ANSWER_BLOCK = layout(10, ANSWER_FIELDS)
PICKS = 10 + sum(f.count for f in ANSWER_FIELDS)  # 30
PICK_STRIDE = sum(f.count for f in PICK_FIELDS)  # 10
PICK_OFFSETS = layout(0, PICK_FIELDS)
MESSAGE_BLOCK = layout(PICKS + PICK_STRIDE * MAX_PICKS, MESSAGE_FIELDS)  # 110
PRODUCTION_BLOCK = layout(MESSAGE_BLOCK["MESSAGE"].end + 1, PRODUCTION_FIELDS)  # 174
SIGMA_SEQ_BLOCK = layout(PRODUCTION_BLOCK["LAST_SIGMA_MDEG"].end + 1, SIGMA_SEQ_FIELDS)  # 203
PICK_SIGMA = SIGMA_SEQ_BLOCK["SIGMA_SEQ"].address + 1  # 204
SIGMA_STRIDE = sum(f.count for f in SIGMA_FIELDS)  # 4
SIGMA_OFFSETS = layout(0, SIGMA_FIELDS)
SIGMA_END = PICK_SIGMA + SIGMA_STRIDE * MAX_PICKS  # 236: the first address after the uncertainty block
DOUBT_BLOCK = layout(SIGMA_END, DOUBT_FIELDS)  # 236
END = DOUBT_BLOCK["DOUBT_SLOT"].end + 1  # 241: the first address after the in-doubt block
CONVEYOR_BLOCK = layout(END, CONVEYOR_FIELDS)  # 241
MAP_END = CONVEYOR_BLOCK["QUEUE_LENGTH"].end + 1  # 244: the first address after the map

REGISTERS: dict[str, Placed] = {**COMMAND_BLOCK, **ANSWER_BLOCK, **MESSAGE_BLOCK, **PRODUCTION_BLOCK, **SIGMA_SEQ_BLOCK,
                                **DOUBT_BLOCK, **CONVEYOR_BLOCK}
"""Every field at a fixed address (the pick and sigma fields repeat: ``PICK_OFFSETS``, ``SIGMA_OFFSETS``)."""


def address(name: str) -> int:
    return REGISTERS[name].address


def int32_words(value: float) -> list[int]:
    """A number as an int32 register pair, big-endian words (high word first), saturated."""
    v = int(round(value)) if math.isfinite(value) else 0
    v = max(-(2**31), min(2**31 - 1, v))
    u = v & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def sigma_words(value: float | None, scale: float) -> list[int]:
    """A 1-sigma as an int32 register pair at ``1 / scale`` resolution: -1 when not known; a positive sigma
    below the resolution reads 1, never 0, so that the PLC is never told a pick is exact."""
    if value is None or not math.isfinite(value) or value < 0:
        return int32_words(-1)
    scaled = value * scale
    return int32_words(max(1, round(scaled)) if scaled > 0 else 0)


def words_int32(words: Sequence[int]) -> int:
    """The inverse of :func:`int32_words`."""
    u = (words[0] << 16) | words[1]
    return u - (1 << 32) if u & 0x80000000 else u


def ascii_words(text: str, n_regs: int = MESSAGE_FIELDS[0].count) -> list[int]:
    """Text as registers, 2 ASCII characters each (high byte first), NUL-padded and truncated."""
    raw = text.encode("ascii", "replace")[: 2 * n_regs].ljust(2 * n_regs, b"\0")
    return [(raw[2 * i] << 8) | raw[2 * i + 1] for i in range(n_regs)]


def words_ascii(words: Sequence[int]) -> str:
    """The inverse of :func:`ascii_words`."""
    raw = b"".join(bytes([w >> 8, w & 0xFF]) for w in words)
    return raw.rstrip(b"\0").decode("ascii", "replace")


PRODUCTION_VALUES: dict[str, tuple[str, float]] = {
    "RUN_ID": ("run_id", 1.0), "RUN_STATE": ("state", 1.0), "ENDED_BECAUSE": ("ended", 1.0),
    "COUNTERS": ("counters", 1.0), "NEXT_SLOT": ("next_slot", 1.0), "LAST_RESULT": ("last_result", 1.0),
    "LAST_SLOT": ("last_slot", 1.0), "CYCLE_MEDIAN_MS": ("cycle_median_ms", 1.0),
    "LAST_SIGMA_UM": ("sigma_mm", 1000.0), "LAST_SIGMA_MDEG": ("sigma_deg", 1000.0),
}
"""Each production field's value in ``cellctl.plc.production.production_values`` and its scale (a
negative value, "not known", is written as -1 unscaled)."""


def field_words(f: Field, value: Any, scale: float = 1.0) -> list[int]:
    """A field's registers from its value (``int32s``: a sequence of numbers)."""
    if f.kind == "int32s":
        words: list[int] = []
        for v in value:
            words += int32_words(v)
        return words
    if f.kind == "int32" and f.name.startswith("LAST_SIGMA"):
        return sigma_words(value, scale)
    if f.kind == "int32":
        return int32_words(value * scale if value >= 0 else -1)
    if f.kind == "ascii":
        return ascii_words(str(value), f.count)
    return [int(value) & 0xFFFF]


def production_block_words(values: dict[str, Any]) -> list[int]:
    """The production block (its registers in order) from ``production_values``' numbers."""
    words: list[int] = []
    for f in PRODUCTION_FIELDS:
        key, scale = PRODUCTION_VALUES[f.name]
        words += field_words(f, values[key], scale)
    return words


def conveyor_block_words(missed_window: int, queue_length: int) -> list[int]:
    """The conveyor block (its registers in order): parts that left the window unpicked in the last run, and
    the parts queued on the belt now (0 for a still run or none)."""
    return [*int32_words(missed_window), max(0, min(0xFFFF, int(queue_length)))]


DOUBT_UNKNOWN = 0xFFFF
"""DOUBT_COUNT when the store cannot be read: what is in doubt is not known."""


def doubt_block_words(count: int | None, recipe_id: int | None, slot: int | None) -> list[int]:
    """The in-doubt block: ``count`` None when not known (``DOUBT_UNKNOWN``), recipe and slot -1 for none."""
    values = {"DOUBT_COUNT": DOUBT_UNKNOWN if count is None else min(count, DOUBT_UNKNOWN - 1),
              "DOUBT_RECIPE": -1 if recipe_id is None else recipe_id, "DOUBT_SLOT": -1 if slot is None else slot}
    words: list[int] = []
    for f in DOUBT_FIELDS:
        words += field_words(f, values[f.name])
    return words
