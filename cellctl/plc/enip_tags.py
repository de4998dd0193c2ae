"""The EtherNet/IP tags of the cell (docs/plc-ethernet-ip.md) and their handshake, protocol-free.

:class:`TagImage` holds what a Logix PLC reads and writes with MSG instructions ("CIP Data Table
Read/Write"); ``cellctl.plc.enip_server`` serves it over CIP (cpppo). Every method runs on the
server's event loop, like the Modbus register image: an answer is posted whole, between two reads.

The handshake is the Modbus one (docs/plc-modbus.md): the PLC writes ``CC_Command``, ``CC_Recipe``
(and ``CC_Count`` for a production start), then a new non-zero ``CC_Sequence``, which starts the
request; ``CC_Status`` bit 0 BUSY is set at once; when ``CC_EchoSeq`` equals the sequence, bit 1
DONE or bit 2 ERROR says how it went and the other tags hold the answer, kept until the next
request. A new sequence while this front end's request runs is refused: the write fails (CIP
status 0xFF, the MSG instruction's .ER) and bit 3 REFUSED is set. ``CC_Heartbeat`` counts up every
100 ms; bits 4/5 (robot latched / owned), the run state, ended-because and the counters are live.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellctl.errors import CellctlError
from cellctl.plc.engine import Request, unknown_command
from cellctl.plc.production import production_values
from cellctl.plc.requests import Outcome, pick_sigma, robot_motion_status
from cellctl.services import Services

BUSY, DONE, ERROR, REFUSED, ROBOT_LATCHED, ROBOT_OWNED, DRIFT_ALARM = 0x1, 0x2, 0x4, 0x8, 0x10, 0x20, 0x40
MAX_PICKS = 8
PICK_FIELDS = ("x_mm", "y_mm", "z_mm", "rz_deg", "score", "reachable", "sigma_mm", "sigma_deg")
"""``CC_Picks``: 8 REALs per pick, in this order (``rz_deg``: the gripper's yaw about base z)."""
MESSAGE_CHARS = 82
"""A Logix STRING holds 82 characters."""


@dataclass(frozen=True)
class TagSpec:
    """A tag: its name, CIP type (cpppo's name), element count and whether the PLC writes it."""

    name: str
    cip_type: str = "DINT"
    count: int = 1
    writable: bool = False


TAGS: tuple[TagSpec, ...] = (
    TagSpec("CC_Command", writable=True), TagSpec("CC_Recipe", writable=True), TagSpec("CC_Count", writable=True),
    TagSpec("CC_Sequence", writable=True),
    TagSpec("CC_Status"), TagSpec("CC_EchoSeq"), TagSpec("CC_ErrorCode"), TagSpec("CC_ErrorText"),
    TagSpec("CC_PicksReported"), TagSpec("CC_Picks", "REAL", MAX_PICKS * len(PICK_FIELDS)),
    TagSpec("CC_Heartbeat"), TagSpec("CC_RunState"), TagSpec("CC_EndedBecause"), TagSpec("CC_Counters", count=7),
    TagSpec("CC_Message", "STRING"),
)
TAG_SPECS = {t.name: t for t in TAGS}


class RefusedWrite(CellctlError):
    """A write the handshake does not take (busy, a read-only tag, a value out of range)."""


class TagImage:
    """The tags' values and the handshake. ``submit`` starts a request and calls back with its answer."""

    def __init__(self, services: Services, submit: Callable[[Request, Callable[[Outcome], None]], None]) -> None:
        self.services = services
        self._submit = submit
        self.values: dict[str, Any] = {t.name: ([0] * t.count if t.count > 1 else 0) for t in TAGS}
        self.values["CC_Picks"] = [0.0] * TAG_SPECS["CC_Picks"].count
        self.values["CC_Message"] = ""
        self.busy = False
        self.last_seq = 0
        self.requests = 0
        self.refused = 0

    # -- reads --------------------------------------------------------------------------------------
    def read(self, name: str) -> Any:
        """A tag's value now (the live ones computed at the read)."""
        if name == "CC_Heartbeat":
            return int(time.monotonic() * 10) & 0x7FFFFFFF
        if name == "CC_Status":
            return (self.values["CC_Status"] & 0xF) | self._robot_bits()
        if name in ("CC_RunState", "CC_EndedBecause", "CC_Counters"):
            v = production_values(self.services)
            return {"CC_RunState": v["state"], "CC_EndedBecause": v["ended"],
                    "CC_Counters": [int(c) for c in v["counters"]]}[name]
        return self.values[name]

    def _robot_bits(self) -> int:
        status = robot_motion_status(self.services)
        drift = self.services.drift_if_made
        alarm = DRIFT_ALARM if drift is not None and drift.alarm else 0
        return (ROBOT_LATCHED if status["latched"] else 0) | (ROBOT_OWNED if status["owner"] else 0) | alarm

    # -- writes -------------------------------------------------------------------------------------
    def write(self, name: str, value: Any) -> None:
        """A PLC's write of a whole tag; raises :class:`RefusedWrite` for what it may not write."""
        spec = TAG_SPECS[name]
        if not spec.writable:
            raise RefusedWrite(f"{name} is read-only (written by the cell)")
        if not isinstance(value, int) or isinstance(value, bool):
            raise RefusedWrite(f"{name} is a DINT")
        if name == "CC_Sequence" and value != 0 and value != self.last_seq:
            if self.busy:
                self.refused += 1
                self.values["CC_Status"] |= REFUSED
                raise RefusedWrite(f"sequence {value} refused: request {self.last_seq} is running")
            self.values[name] = value
            self._accept(value)
            return
        self.values[name] = value

    def _accept(self, seq: int) -> None:
        command, recipe, count = (int(self.values[k]) for k in ("CC_Command", "CC_Recipe", "CC_Count"))
        self.requests += 1
        self.last_seq = seq
        self.busy = True
        self.values["CC_Status"] = BUSY
        request = Request.from_command(command, recipe, count)
        if request is None:
            self.post(seq, unknown_command(command))
            return
        self._submit(request, lambda out: self.post(seq, out))

    def post(self, seq: int, out: Outcome) -> None:
        """Write the whole answer at once."""
        picks = out.picks[:MAX_PICKS]
        flat = [0.0] * TAG_SPECS["CC_Picks"].count
        for k, p in enumerate(picks):
            pose = p["pick_pose"]
            sigma_mm, sigma_deg = pick_sigma(p)
            row = [pose["x_mm"], pose["y_mm"], pose["z_mm"], p["gripper_yaw_deg"], p["score"],
                   1.0 if p["reachable"] else 0.0, -1.0 if sigma_mm is None else sigma_mm,
                   -1.0 if sigma_deg is None else sigma_deg]
            flat[k * len(PICK_FIELDS) : (k + 1) * len(PICK_FIELDS)] = [float(x) for x in row]
        v = self.values
        v["CC_Picks"] = flat
        v["CC_PicksReported"] = len(picks)
        v["CC_ErrorCode"] = out.error_class
        v["CC_ErrorText"] = out.text_index
        v["CC_Message"] = "" if out.ok else out.message.encode("ascii", "replace").decode()[:MESSAGE_CHARS]
        v["CC_EchoSeq"] = seq
        v["CC_Status"] = (v["CC_Status"] & REFUSED) | (DONE if out.ok else ERROR)
        self.busy = False
