"""The Modbus TCP server for PLCs: pick, verify and production through holding registers (pymodbus 3.16).

The PLC is the Modbus client; ``cellctl serve`` answers on ``plc.modbus.host:port`` (unit id
``plc.modbus.unit_id``). All data are 16-bit holding registers, read with FC3 (or FC4, same
registers) and written with FC6/FC16; every other function code (7, 8, 11, 17, 20, 21, 24, 43, ...)
is answered exception 01. Addresses are protocol addresses, 0-based. Unmapped addresses and writes
to the read-only block answer exception 02 (illegal data address); other unit ids exception 0B.

The register map is one table in code, ``cellctl.plc.modbus_map`` (map version ``MAP_VERSION``);
the addresses below come from it and docs/plc-modbus.md describes it (a test holds the two together).

Handshake: write COMMAND, RECIPE, SEQUENCE (one FC16 at 0, count 3) with a new SEQUENCE; when the
write is answered BUSY is set and DONE/ERROR are clear; poll 10..109 in one FC3 read until ECHO_SEQ
equals your SEQUENCE, then DONE or ERROR tells the outcome and the rest of the snapshot is the
answer. While this server's request runs, a new SEQUENCE is refused with exception 06 (REFUSED,
REFUSED_SEQ); while another front end's request runs, the request is answered ERROR, text 2 (busy),
by the request engine (``cellctl.plc.engine``), which runs every front end's requests one at a time.

Connections: at most ``max_connections`` at once and ``max_connections_per_address`` from one
address (more are closed at once); one silent for ``idle_timeout_s`` is closed; a frame that cannot
be decoded closes its connection with one rate-limited log line, never a traceback. The requests'
work is paced (``cellctl.plc.pacing``) so that a client polling as fast as it is answered cannot
take the interpreter from Stop.

The server runs in its own thread with its own event loop; requests run in the engine's worker
thread, so a slow pick never delays register reads.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from cellctl.config_listeners import ModbusServerConfig, is_loopback_host
from cellctl.plc import modbus_map as mm
from cellctl.plc.engine import Engine, FrontEnd, Request, engine_for, unknown_command
from cellctl.plc.modbus_map import (  # noqa: F401 - re-exported: the PLC tests and bench decode with them
    MAP_VERSION,
    MAX_PICKS,
    PICK_SIGMA,
    PICK_STRIDE,
    PICKS,
    SIGMA_STRIDE,
    ascii_words,
    int32_words,
    sigma_words,
    words_ascii,
    words_int32,
)
from cellctl.plc.pacing import Pacer
from cellctl.plc.production import conveyor_words, doubt_words, production_words
from cellctl.plc.quiet_log import client_mistake, quiet
from cellctl.plc.requests import ERROR_TEXTS, Outcome, failure, pick_sigma, robot_motion_status
from cellctl.services import Services
from drivers.loop_thread import LoopNotRunning, LoopThread

log = logging.getLogger(__name__)

_a = mm.address
COMMAND, RECIPE, SEQUENCE, COUNT = _a("COMMAND"), _a("RECIPE"), _a("SEQUENCE"), _a("COUNT")
STATUS, ECHO_SEQ, ACTIVE_SEQ, ERROR_CODE, ERROR_TEXT = (_a("STATUS"), _a("ECHO_SEQ"), _a("ACTIVE_SEQ"),
                                                        _a("ERROR_CODE"), _a("ERROR_TEXT"))
RESULT_COMMAND, PICKS_REPORTED, PICKS_FOUND, VERIFY_PASSED, REFUSED_SEQ = (
    _a("RESULT_COMMAND"), _a("PICKS_REPORTED"), _a("PICKS_FOUND"), _a("VERIFY_PASSED"), _a("REFUSED_SEQ"))
DRIFT_PX, DRIFT_MM, LATENCY, HEARTBEAT = _a("DRIFT_PX"), _a("DRIFT_MM"), _a("LATENCY"), _a("HEARTBEAT")
MAX_PICKS_REG, MAP_VERSION_REG, PICKED = _a("MAX_PICKS"), _a("MAP_VERSION"), _a("PICKED")
MESSAGE = _a("MESSAGE")  # 110
MESSAGE_REGS = mm.REGISTERS["MESSAGE"].field.count
PRODUCTION = _a("RUN_ID")  # 174: the production block (live on every read)
PRODUCTION_REGS = sum(f.count for f in mm.PRODUCTION_FIELDS)
SIGMA_SEQ = _a("SIGMA_SEQ")  # 203: the per-pick uncertainty block
SIGMA_END = mm.SIGMA_END  # 236: first address after the uncertainty block
DOUBT = _a("DOUBT_COUNT")  # 236: the slots in doubt (live on every read)
END = mm.END  # 241: first address after the in-doubt block
MAP_END = mm.MAP_END  # 244: first address after the map (the conveyor block 241..243, live on every read)
READ_ONLY = STATUS
_PICK = {name: placed.address for name, placed in mm.PICK_OFFSETS.items()}
_SIGMA = {name: placed.address for name, placed in mm.SIGMA_OFFSETS.items()}

BUSY, DONE, ERROR, REFUSED, ROBOT_LATCHED, ROBOT_OWNED, DRIFT_ALARM = (
    1 << mm.STATUS_BITS[name] for name in ("BUSY", "DONE", "ERROR", "REFUSED", "ROBOT_LATCHED", "ROBOT_OWNED",
                                           "DRIFT_ALARM"))
LIVE_BITS = ROBOT_LATCHED | ROBOT_OWNED | DRIFT_ALARM
CMD_IDLE, CMD_PICK, CMD_VERIFY, CMD_PICK_MOVE = 0, 1, 2, 3
ALLOWED_FUNCTIONS = (3, 4, 6, 16)
IDLE_CHECK_S = 1.0


async def _gateway_no_response(function_code: int, start_address: int, address: int, count: int,
                               registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes:
    return ExcCodes.GATEWAY_NO_RESPONSE


is_loopback = is_loopback_host


class _Connection(ServerRequestHandler):  # type: ignore[misc]
    """One client connection: admitted under the caps, closed when idle or on garbage, and only the
    documented function codes served (every other one: exception 01)."""

    plc: ModbusPlcServer
    peer = "?"
    last_activity = 0.0

    def callback_connected(self) -> None:
        super().callback_connected()
        info = self.transport.get_extra_info("peername") if self.transport else None
        self.peer = str(info[0]) if info else "?"
        self.last_activity = time.monotonic()
        if not self.plc._admit(self):
            self.close()

    def callback_disconnected(self, exc: Exception | None) -> None:
        self.plc._forget(self)
        super().callback_disconnected(exc)

    def close(self, reconnect: bool = False) -> None:
        self.plc._forget(self)
        super().close(reconnect)

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        self.last_activity = time.monotonic()
        try:
            used: int = super().callback_data(data, addr)
            return used
        except Exception as exc:  # noqa: BLE001 - a client's garbage closes its connection, nothing more
            client_mistake(log, "undecodable Modbus frames", "PLC Modbus: closed the connection from %s: a frame "
                           "that is not Modbus TCP (%s)", self.peer, str(exc).splitlines()[0][:120] if str(exc)
                           else type(exc).__name__)
            self.close()
            return len(data)

    async def handle_request(self) -> None:
        pdu = self.last_pdu
        if pdu is None:
            return
        if pdu.function_code not in ALLOWED_FUNCTIONS:
            response = ExceptionResponse(pdu.function_code & 0x7F, ExcCodes.ILLEGAL_FUNCTION)
            response.transaction_id = pdu.transaction_id
            response.dev_id = pdu.dev_id
            self.server_send(response, self.last_addr)
            return
        try:
            t0 = await self.plc.pacer.wait()
            self.last_pdu = pdu  # the request this call was scheduled for, whatever came meanwhile
            await super().handle_request()
            self.plc.pacer.done(t0)
        except Exception as exc:  # noqa: BLE001 - never a traceback for a client's request
            client_mistake(log, "failed Modbus requests", "PLC Modbus: a request from %s failed (%s); connection "
                           "closed", self.peer, type(exc).__name__)
            self.close()


class _TcpServer(ModbusTcpServer):  # type: ignore[misc]
    plc: ModbusPlcServer

    def callback_new_connection(self) -> _Connection:
        conn = _Connection(self, self.trace_packet, self.trace_pdu, self.trace_connect)
        conn.plc = self.plc
        return conn


class ModbusPlcServer:
    """The PLC's Modbus TCP server for one cell; ``start()`` listens, ``stop()`` ends it."""

    def __init__(self, services: Services, host: str = "127.0.0.1", port: int = 5020, unit_id: int = 1,
                 config: ModbusServerConfig | None = None, engine: Engine | None = None) -> None:
        self.services, self.host, self.port, self.unit_id = services, host, port, unit_id
        self.config = config or ModbusServerConfig(host=host, port=port, unit_id=unit_id)
        self.engine = engine or engine_for(services)
        self._image = [0] * MAP_END
        """The read-only block as the PLC sees it; changed only on the server's loop."""
        self._image[MAX_PICKS_REG] = MAX_PICKS
        self._image[MAP_VERSION_REG] = MAP_VERSION
        self._busy = False
        self._last_seq = 0
        self._accepted_at = 0.0
        self._thread = LoopThread(f"plc-modbus-{port}")
        self._server: _TcpServer | None = None
        self._front: FrontEnd | None = None
        self._connections: set[_Connection] = set()
        self._idle_task: asyncio.Task[None] | None = None
        self.requests = 0
        self.refused = 0
        self.closed_idle = 0
        self.closed_over_cap = 0
        self.pacer = Pacer()
        """Bounds the share of the interpreter the clients' requests take (``cellctl.plc.pacing``)."""

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> ModbusPlcServer:
        quiet("pymodbus")
        self._front = self.engine.register("modbus", self.host, self.port)
        self._front.pacer = self.pacer

        async def serve() -> None:
            server = _TcpServer(self._devices(), address=(self.host, self.port))
            server.plc = self
            self._server = server
            try:
                await server.serve_forever(background=True)
            except (RuntimeError, OSError) as exc:
                raise OSError(f"PLC Modbus server cannot listen on {self.host}:{self.port} ({exc}); "
                              "free the port or change plc.modbus.port") from None
            self._idle_task = asyncio.get_running_loop().create_task(self._close_idle())

        try:
            self._thread.start(serve)
        except BaseException:
            self.engine.unregister("modbus")
            raise
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
            if self._idle_task is not None:
                self._idle_task.cancel()
            if self._server is not None:
                await self._server.shutdown()

        self._thread.stop(shutdown)
        self.engine.unregister("modbus")

    def _devices(self) -> list[SimDevice]:
        ours = SimDevice(
            id=self.unit_id,
            simdata=[
                SimData(COMMAND, count=4, values=0, datatype=DataType.REGISTERS),
                SimData(READ_ONLY, count=MAP_END - READ_ONLY, values=0, datatype=DataType.REGISTERS, readonly=True),
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

    # -- connections (all on the server's loop) -----------------------------------------------------
    def _admit(self, conn: _Connection) -> bool:
        cfg = self.config
        same = sum(1 for c in self._connections if c.peer == conn.peer)
        if len(self._connections) >= cfg.max_connections or same >= cfg.max_connections_per_address:
            self.closed_over_cap += 1
            client_mistake(log, "Modbus connections over the cap", "PLC Modbus: refused a connection from %s (%d "
                           "from that address, %d in all; caps %d and %d: plc.modbus.max_connections_per_address, "
                           "max_connections)", conn.peer, same, len(self._connections),
                           cfg.max_connections_per_address, cfg.max_connections)
            return False
        self._connections.add(conn)
        if self._front is not None:
            self._front.clients = len(self._connections)
        return True

    def _forget(self, conn: _Connection) -> None:
        self._connections.discard(conn)
        if self._front is not None:
            self._front.clients = len(self._connections)

    async def _close_idle(self) -> None:
        """Close connections silent for ``idle_timeout_s`` (checked every second)."""
        while True:
            await asyncio.sleep(min(IDLE_CHECK_S, self.config.idle_timeout_s / 2))
            limit = time.monotonic() - self.config.idle_timeout_s
            for conn in [c for c in self._connections if c.last_activity < limit]:
                self.closed_idle += 1
                client_mistake(log, "idle Modbus connections", "PLC Modbus: closed the connection from %s: silent "
                               "for %.0f s (plc.modbus.idle_timeout_s)", conn.peer, self.config.idle_timeout_s)
                conn.close()

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
            self._image[END:MAP_END] = conveyor_words(self.services)
        except Exception:  # noqa: BLE001 - the register map is served whatever the run's state
            log.exception("reading the production run's state failed")
        self._image[DOUBT:END] = doubt_words(self.services)
        registers[READ_ONLY - start_address : MAP_END - start_address] = self._image[READ_ONLY:MAP_END]

    def _robot_bits(self) -> int:
        """ROBOT_LATCHED / ROBOT_OWNED of the cell's robot and DRIFT_ALARM now (locks, no I/O: fine on the loop)."""
        try:
            status = robot_motion_status(self.services)
        except Exception:  # noqa: BLE001 - the register map is served whatever the robot's state
            log.exception("reading the robot's motion status failed")
            return 0
        drift = self.services.drift_if_made  # a lock, no I/O
        alarm = DRIFT_ALARM if drift is not None and drift.alarm else 0
        return (ROBOT_LATCHED if status["latched"] else 0) | (ROBOT_OWNED if status["owner"] else 0) | alarm

    def _accept(self, command: int, recipe: int, seq: int, count: int = 0) -> None:
        self.requests += 1
        self._last_seq = seq
        self._busy = True
        self._accepted_at = time.perf_counter()
        img = self._image
        img[STATUS] = BUSY
        img[ACTIVE_SEQ] = seq
        request = Request.from_command(command, recipe, count)
        if request is None:
            self._post(seq, command, unknown_command(command))
            return
        if self._front is None:
            raise LoopNotRunning("the Modbus server is not started: start() registers its front end")
        future = self.engine.submit(self._front, request, "plc:modbus")
        if future.done():  # answered at once (idle, refused busy): posted before the write is acknowledged
            self._post(seq, command, future.result())
            return
        wrapped = asyncio.wrap_future(future)

        def finished(f: asyncio.Future[Outcome]) -> None:
            outcome = f.result() if not f.cancelled() else failure(99, "the request was cancelled (server shutting "
                                                                       "down)")
            self._post(seq, command, outcome)

        wrapped.add_done_callback(finished)

    def _post(self, seq: int, command: int, out: Outcome) -> None:
        """Write the whole answer at once (the loop never interleaves a read with this)."""
        img = self._image
        picks = out.picks[:MAX_PICKS]
        img[PICKS:PRODUCTION] = [0] * (PRODUCTION - PICKS)
        for k, p in enumerate(picks):
            pose = p["pick_pose"]
            base = PICKS + PICK_STRIDE * k
            for name, value in (("X", pose["x_mm"] * 100), ("Y", pose["y_mm"] * 100), ("Z", pose["z_mm"] * 100),
                                ("ROTATION", p["gripper_yaw_deg"] * 1000)):
                img[base + _PICK[name] : base + _PICK[name] + 2] = int32_words(value)
            img[base + _PICK["SCORE"]] = max(0, min(1000, int(round(float(p["score"]) * 1000))))
            img[base + _PICK["REACHABLE"]] = 1 if p["reachable"] else 0
        img[SIGMA_SEQ:SIGMA_END] = [0] + [0xFFFF] * (SIGMA_END - PICK_SIGMA)  # -1: not known
        for k, p in enumerate(picks):
            sigma_mm, sigma_deg = pick_sigma(p)
            base = PICK_SIGMA + SIGMA_STRIDE * k
            img[base + _SIGMA["SIGMA_UM"] : base + _SIGMA["SIGMA_UM"] + 2] = sigma_words(sigma_mm, 1000)
            img[base + _SIGMA["SIGMA_MDEG"] : base + _SIGMA["SIGMA_MDEG"] + 2] = sigma_words(sigma_deg, 1000)
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
