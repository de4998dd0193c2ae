"""The Modbus TCP server for PLCs: pick and verify through holding registers (pymodbus 3.16).

The PLC is the Modbus client; ``cellctl serve`` answers on ``plc.modbus.host:port`` (unit id
``plc.modbus.unit_id``). All data are 16-bit holding registers, read with FC3 (or FC4, same
registers) and written with FC6/FC16; other function codes are refused (exception 01). Addresses
are protocol addresses, 0-based (the "4x" reference is 40001 + address). Unmapped addresses and
writes to the read-only block answer exception 02 (illegal data address); other unit ids
exception 0B.

Register map (version 4; full description with the handshake in docs/plc-modbus.md)::

    address  dir  meaning
    0        W    COMMAND: 0 idle (no-op, answered at once), 1 pick (recipe in 1), 2 verify calibration,
                  3 pick with robot motion (recipe in 1; only with plc.allow_motion: true), 4..7
                  production start (recipe in 1, count in 3; plc.allow_motion), pause, resume, stop
    1        W    RECIPE: recipe number 0..65535
    2        W    SEQUENCE: request counter 1..65535 written by the PLC (0 = no request). A write that
                  changes it to a new non-zero value starts the request latched from 0..2 (write 0..2
                  in one FC16). While BUSY such a write is refused with exception 06 (device busy),
                  not applied, and flagged with REFUSED / REFUSED_SEQ; the running request goes on.
    3        W    COUNT: production start: parts to place, 0 = until the area is empty (write 0..3 in one FC16)
    10       R    STATUS bits: bit0 BUSY, bit1 DONE (answer ok), bit2 ERROR (answer failed),
                  bit3 REFUSED (the last sequence write was refused: busy), live on every read:
                  bit4 ROBOT_LATCHED (the cell's robot is stopped until an engineer resumes it),
                  bit5 ROBOT_OWNED (a move, pick or routine owns the robot's motion now)
    11       R    ECHO_SEQ: the sequence of the request the answer (10, 13..173) belongs to; 0 = none yet
    12       R    ACTIVE_SEQ: the sequence of the running request (the last accepted one when idle)
    13       R    ERROR_CODE: error class (0 none, 1 request, 2 busy, 3 setup, 4 runtime, 5 drift,
                  6 robot stopped, 9 internal)
    14       R    ERROR_TEXT: error-text index (table in docs/plc-modbus.md, cellctl.plc.requests.ERROR_TEXTS)
    15       R    RESULT_COMMAND: the command the answer is for
    16       R    PICKS_REPORTED: picks in 30..109 (at most MAX_PICKS)
    17       R    PICKS_FOUND: all picks found (may exceed MAX_PICKS)
    18       R    VERIFY_PASSED: 1 when the verify passed, else 0
    19       R    REFUSED_SEQ: the sequence of the last refused request
    20-21    R    DRIFT_PX x1000, int32 (verify; -1 when not measured)
    22-23    R    DRIFT_MM x1000, int32 (verify; -1 when not measured: no hand-eye calibration)
    24-25    R    LATENCY in 0.1 ms, int32: request accepted -> answer posted
    26       R    HEARTBEAT: counts up every 100 ms while the server runs (wraps at 65536)
    27       R    MAX_PICKS (8)
    28       R    MAP_VERSION (2)
    29       R    PICKED: command 3 only: k + 1 when the robot picked pick k; 0 when it did not move
    30+10k   R    pick k (k = 0..7, best first):
                    +0..1 X, +2..3 Y, +4..5 Z of the gripper pick pose in the robot base frame, int32 in 0.01 mm
                    +6..7 ROTATION: gripper yaw about base z, int32 in 0.001 degree
                    +8 SCORE x1000 (0..1000), +9 REACHABLE (1: inside the envelope, 0: do not send it)
    110-173  R    MESSAGE: the error's one-line text, ASCII, 2 characters per register (high byte
                  first), NUL-padded, at most 128 characters
    174-202  R    PRODUCTION: the production run's state, live on every read (docs/plc-modbus.md):
                  run id, state, ended_because, counters, next slot, the last cycle's result, slot,
                  cycle time and 1-sigma uncertainty
    203      R    SIGMA_SEQ: the sequence of the answer 204..235 belong to (= ECHO_SEQ once posted)
    204+4k   R    pick k's 1-sigma (k = 0..7, as 30+10k): +0..1 position (largest axis), int32 in um;
                  +2..3 angle, int32 in 0.001 degree; -1 when not known

int32 values are two registers, **big-endian words: high word first**, two's complement.

Handshake: write COMMAND, RECIPE, SEQUENCE (one FC16 at 0, count 3) with a new SEQUENCE; when the
write is answered BUSY is set and DONE/ERROR are clear; poll 10..109 in one FC3 read (100
registers, one consistent snapshot) until ECHO_SEQ equals your SEQUENCE, then DONE or ERROR
tells the outcome and the rest of the snapshot is the answer. The answer stays until the next
request, so a PLC that lost its connection reconnects and reads it; writing the same SEQUENCE
again starts nothing.

The server runs in its own thread with its own event loop; picks and verifies run in a worker
thread (one at a time), so a slow pick never delays register reads.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from cellctl.config import is_loopback_host
from cellctl.plc.production import PRODUCTION_COMMANDS, execute_production, production_words
from cellctl.plc.requests import (
    ERROR_TEXTS,
    TEXT_UNKNOWN_COMMAND,
    Outcome,
    execute_pick,
    execute_verify,
    failure,
    pick_sigma,
    robot_motion_status,
)
from cellctl.services import Services
from drivers.loop_thread import LoopThread

log = logging.getLogger(__name__)

MAP_VERSION = 4
COMMAND, RECIPE, SEQUENCE, COUNT = 0, 1, 2, 3
STATUS, ECHO_SEQ, ACTIVE_SEQ, ERROR_CODE, ERROR_TEXT = 10, 11, 12, 13, 14
RESULT_COMMAND, PICKS_REPORTED, PICKS_FOUND, VERIFY_PASSED, REFUSED_SEQ = 15, 16, 17, 18, 19
DRIFT_PX, DRIFT_MM, LATENCY, HEARTBEAT, MAX_PICKS_REG, MAP_VERSION_REG, PICKED = 20, 22, 24, 26, 27, 28, 29
PICKS = 30
PICK_STRIDE = 10
MAX_PICKS = 8
MESSAGE = PICKS + PICK_STRIDE * MAX_PICKS  # 110
MESSAGE_REGS = 64
PRODUCTION = MESSAGE + MESSAGE_REGS  # 174: the production block (live on every read)
PRODUCTION_REGS = 29
SIGMA_SEQ = PRODUCTION + PRODUCTION_REGS  # 203: the per-pick uncertainty block (map version 4)
PICK_SIGMA = SIGMA_SEQ + 1  # 204 + 4k: pick k's position and angle 1-sigma
SIGMA_STRIDE = 4
END = PICK_SIGMA + SIGMA_STRIDE * MAX_PICKS  # 236: first address after the map
READ_ONLY = STATUS

BUSY, DONE, ERROR, REFUSED, ROBOT_LATCHED, ROBOT_OWNED = 0x1, 0x2, 0x4, 0x8, 0x10, 0x20
LIVE_BITS = ROBOT_LATCHED | ROBOT_OWNED
CMD_IDLE, CMD_PICK, CMD_VERIFY, CMD_PICK_MOVE = 0, 1, 2, 3
ALLOWED_FUNCTIONS = (3, 4, 6, 16)


async def _gateway_no_response(function_code: int, start_address: int, address: int, count: int,
                               registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes:
    return ExcCodes.GATEWAY_NO_RESPONSE


is_loopback = is_loopback_host


def int32_words(value: float) -> list[int]:
    """A number as an int32 register pair, big-endian words (high word first), saturated."""
    v = int(round(value)) if math.isfinite(value) else 0
    v = max(-(2**31), min(2**31 - 1, v))
    u = v & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def words_int32(words: Sequence[int]) -> int:
    """The inverse of :func:`int32_words`."""
    u = (words[0] << 16) | words[1]
    return u - (1 << 32) if u & 0x80000000 else u


def ascii_words(text: str, n_regs: int = MESSAGE_REGS) -> list[int]:
    """Text as registers, 2 ASCII characters each (high byte first), NUL-padded and truncated."""
    raw = text.encode("ascii", "replace")[: 2 * n_regs].ljust(2 * n_regs, b"\0")
    return [(raw[2 * i] << 8) | raw[2 * i + 1] for i in range(n_regs)]


def words_ascii(words: Sequence[int]) -> str:
    """The inverse of :func:`ascii_words`."""
    raw = b"".join(bytes([w >> 8, w & 0xFF]) for w in words)
    return raw.rstrip(b"\0").decode("ascii", "replace")


class ModbusPlcServer:
    """The PLC's Modbus TCP server for one cell; ``start()`` listens, ``stop()`` ends it."""

    def __init__(self, services: Services, host: str = "127.0.0.1", port: int = 5020, unit_id: int = 1) -> None:
        self.services, self.host, self.port, self.unit_id = services, host, port, unit_id
        self._image = [0] * END
        """The read-only block as the PLC sees it; changed only on the server's loop."""
        self._image[MAX_PICKS_REG] = MAX_PICKS
        self._image[MAP_VERSION_REG] = MAP_VERSION
        self._busy = False
        self._last_seq = 0
        self._accepted_at = 0.0
        self._thread = LoopThread(f"plc-modbus-{port}")
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plc-modbus-request")
        self._server: ModbusTcpServer | None = None
        self.requests = 0
        self.refused = 0

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> ModbusPlcServer:
        async def serve() -> None:
            self._server = ModbusTcpServer(self._devices(), address=(self.host, self.port))
            try:
                await self._server.serve_forever(background=True)
            except (RuntimeError, OSError) as exc:
                raise OSError(f"PLC Modbus server cannot listen on {self.host}:{self.port} ({exc}); "
                              "free the port or change plc.modbus.port") from None

        self._thread.start(serve)
        log.info("PLC Modbus TCP server on %s:%d (unit id %d, register map v%d)", self.host, self.port,
                 self.unit_id, MAP_VERSION)
        if not is_loopback(self.host):
            log.warning("PLC Modbus TCP server on %s: Modbus has no authentication; keep this address on the "
                        "PLC's network only", self.host)
        if self.services.config.plc.allow_motion:
            log.warning("plc.allow_motion is on: any Modbus client that reaches %s:%d may make the robot pick "
                        "(command 3)%s", self.host, self.port, "" if is_loopback(self.host) else
                        " (plc.insecure_plc_network: true, the integrator's IEC 62443 zone decision)")
        return self

    def stop(self) -> None:
        async def shutdown() -> None:
            if self._server is not None:
                await self._server.shutdown()

        self._thread.stop(shutdown)
        self._executor.shutdown(wait=True, cancel_futures=True)

    def _devices(self) -> list[SimDevice]:
        ours = SimDevice(
            id=self.unit_id,
            simdata=[
                SimData(COMMAND, count=4, values=0, datatype=DataType.REGISTERS),
                SimData(READ_ONLY, count=END - READ_ONLY, values=0, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._action,
        )
        if self.unit_id == 0:
            return [ours]
        # Every other unit id: exception 0B. (pymodbus 3.16's SimCore would raise a KeyError for an
        # unknown id, answered as exception 04 with a traceback in the log.)
        others = SimDevice(id=0, simdata=[SimData(0, count=65536, values=0, datatype=DataType.REGISTERS)],
                           action=_gateway_no_response)
        return [ours, others]

    # -- requests (all on the server's loop) --------------------------------------------------------
    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        if function_code not in ALLOWED_FUNCTIONS:
            return ExcCodes.ILLEGAL_FUNCTION
        answer: ExcCodes | None = None
        if set_values and address <= SEQUENCE < address + len(set_values):
            block = [int(registers[a - start_address]) for a in (COMMAND, RECIPE, SEQUENCE, COUNT)]
            for i, v in enumerate(set_values):
                if address + i <= COUNT:
                    block[address + i] = int(v)
            seq = block[SEQUENCE]
            if seq != 0 and seq != self._last_seq:
                if self._busy:
                    self.refused += 1
                    self._image[STATUS] |= REFUSED
                    self._image[REFUSED_SEQ] = seq
                    log.warning("PLC Modbus request %d refused: request %d is running", seq, self._last_seq)
                    answer = ExcCodes.DEVICE_BUSY
                else:
                    self._accept(block[COMMAND], block[RECIPE], seq, block[COUNT])
        self._publish(registers, start_address)
        return answer

    def _publish(self, registers: list[int], start_address: int) -> None:
        self._image[HEARTBEAT] = int(time.monotonic() * 10) & 0xFFFF
        self._image[STATUS] = (self._image[STATUS] & ~LIVE_BITS) | self._robot_bits()
        try:
            self._image[PRODUCTION:SIGMA_SEQ] = production_words(self.services)
        except Exception:  # noqa: BLE001 - the register map is served whatever the run's state
            log.exception("reading the production run's state failed")
        registers[READ_ONLY - start_address : END - start_address] = self._image[READ_ONLY:END]

    def _robot_bits(self) -> int:
        """ROBOT_LATCHED / ROBOT_OWNED of the cell's robot now (a lock, no I/O: fine on the loop)."""
        try:
            status = robot_motion_status(self.services)
        except Exception:  # noqa: BLE001 - the register map is served whatever the robot's state
            log.exception("reading the robot's motion status failed")
            return 0
        return (ROBOT_LATCHED if status["latched"] else 0) | (ROBOT_OWNED if status["owner"] else 0)

    def _accept(self, command: int, recipe: int, seq: int, count: int = 0) -> None:
        self.requests += 1
        self._last_seq = seq
        self._busy = True
        self._accepted_at = time.perf_counter()
        img = self._image
        img[STATUS] = BUSY
        img[ACTIVE_SEQ] = seq
        if command == CMD_IDLE:
            self._post(seq, command, Outcome(True))
        elif command == CMD_PICK:
            self._run(seq, command, lambda: execute_pick(self.services, recipe, "plc:modbus"))
        elif command == CMD_VERIFY:
            self._run(seq, command, lambda: execute_verify(self.services, "plc:modbus"))
        elif command == CMD_PICK_MOVE:
            self._run(seq, command, lambda: execute_pick(self.services, recipe, "plc:modbus", move=True))
        elif command in PRODUCTION_COMMANDS:
            self._run(seq, command, lambda: execute_production(self.services, command, recipe, count, "plc:modbus"))
        else:
            self._post(seq, command, failure(TEXT_UNKNOWN_COMMAND, f"unknown command code {command}: use 0 idle, "
                                                                   "1 pick, 2 verify, 3 pick with motion, 4..7 "
                                                                   "production start, pause, resume, stop"))

    def _run(self, seq: int, command: int, work: Any) -> None:
        future = asyncio.get_running_loop().run_in_executor(self._executor, work)

        def finished(f: asyncio.Future[Outcome]) -> None:
            if f.cancelled():
                outcome = failure(99, "the request was cancelled (server shutting down)")
            elif f.exception() is not None:
                outcome = failure(99, f"internal error: {f.exception()}")
            else:
                outcome = f.result()
            self._post(seq, command, outcome)

        future.add_done_callback(finished)

    def _post(self, seq: int, command: int, out: Outcome) -> None:
        """Write the whole answer at once (the loop never interleaves a read with this)."""
        img = self._image
        picks = out.picks[:MAX_PICKS]
        img[PICKS:PRODUCTION] = [0] * (PRODUCTION - PICKS)
        for k, p in enumerate(picks):
            pose = p["pick_pose"]
            base = PICKS + PICK_STRIDE * k
            img[base : base + 2] = int32_words(pose["x_mm"] * 100)
            img[base + 2 : base + 4] = int32_words(pose["y_mm"] * 100)
            img[base + 4 : base + 6] = int32_words(pose["z_mm"] * 100)
            img[base + 6 : base + 8] = int32_words(p["gripper_yaw_deg"] * 1000)
            img[base + 8] = max(0, min(1000, int(round(float(p["score"]) * 1000))))
            img[base + 9] = 1 if p["reachable"] else 0
        img[SIGMA_SEQ:END] = [0] + [0xFFFF] * (END - PICK_SIGMA)  # -1: not known
        for k, p in enumerate(picks):
            sigma_mm, sigma_deg = pick_sigma(p)
            base = PICK_SIGMA + SIGMA_STRIDE * k
            img[base : base + 2] = int32_words(-1 if sigma_mm is None else sigma_mm * 1000)
            img[base + 2 : base + 4] = int32_words(-1 if sigma_deg is None else sigma_deg * 1000)
        img[SIGMA_SEQ] = seq
        v = out.verify or {}
        drift_px, drift_mm = v.get("drift_px"), v.get("drift_mm")
        img[DRIFT_PX : DRIFT_PX + 2] = int32_words(drift_px * 1000 if drift_px is not None else -1)
        img[DRIFT_MM : DRIFT_MM + 2] = int32_words(drift_mm * 1000 if drift_mm is not None else -1)
        img[VERIFY_PASSED] = 1 if v.get("passed") else 0
        img[PICKED] = 0 if out.picked_index is None else out.picked_index + 1
        img[PICKS_REPORTED] = len(picks)
        img[PICKS_FOUND] = min(len(out.picks), 0xFFFF)
        img[RESULT_COMMAND] = command & 0xFFFF
        img[ERROR_CODE] = out.error_class
        img[ERROR_TEXT] = out.text_index
        img[MESSAGE:PRODUCTION] = ascii_words("" if out.ok else out.message)
        img[LATENCY : LATENCY + 2] = int32_words((time.perf_counter() - self._accepted_at) * 1e4)
        img[ECHO_SEQ] = seq
        img[STATUS] = (img[STATUS] & REFUSED) | (DONE if out.ok else ERROR) | self._robot_bits()
        self._busy = False
        if out.ok:
            log.info("PLC Modbus request %d (command %d) done: %d picks", seq, command, len(out.picks))
        else:
            log.info("PLC Modbus request %d (command %d) failed: %s [%s]", seq, command, out.message,
                     ERROR_TEXTS[out.text_index][1])
