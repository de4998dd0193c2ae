"""The one request engine behind every PLC front end (Modbus TCP, OPC UA, EtherNet/IP, robot socket).

A front end is a thin translation: it turns its protocol's request into a :class:`Request`, hands it
to :meth:`Engine.submit` (or :meth:`Engine.run` from a worker thread) and turns the
:class:`~cellctl.plc.requests.Outcome` back into its protocol. The engine holds the rules, the same
for every front end:

- **one request at a time for the cell**: a request arriving while another (from any front end) runs
  is refused at once with ``TEXT_BUSY`` (error class 2, "wait until BUSY clears, then send again");
  production pause and stop are never refused (a stop always gets through, :data:`URGENT`);
- ``plc.allow_motion``: a pick with motion and a production start or resume need it (the request
  functions check it: ``TEXT_MOTION_OFF``);
- the IEC 62443 zone key: a front end that may move the robot (:attr:`FrontEnd.motion`) on an address
  other than loopback needs ``plc.insecure_plc_network`` (:meth:`Engine.register` refuses otherwise);
- the robot's Stop latch and motion owner are checked by the pick and production code themselves
  (``TEXT_ROBOT_STOPPED`` / ``TEXT_ROBOT_BUSY``), as for REST;
- the answer is kept until the front end's next request (:attr:`FrontEnd.last_answer`).

Requests run in the engine's own worker thread (one), never on a front end's event loop; production
pause/stop run in a second worker so that they never wait behind a pick. ``Engine.close`` joins both.
``GET /plc/status`` shows :meth:`Engine.status`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from cellctl.config_listeners import is_loopback_host
from cellctl.plc.pacing import Pacer
from cellctl.plc.requests import (
    TEXT_BUSY,
    TEXT_INTERNAL,
    TEXT_UNKNOWN_COMMAND,
    Outcome,
    execute_pick,
    execute_verify,
    failure,
)
from cellctl.services import Services

log = logging.getLogger(__name__)


class Kind(StrEnum):
    """What a PLC may ask; the value of each is its Modbus COMMAND code's name (docs/plc-modbus.md)."""

    IDLE = "idle"
    PICK = "pick"
    VERIFY = "verify"
    PICK_MOVE = "pick_move"
    PRODUCTION_START = "production_start"
    PRODUCTION_PAUSE = "production_pause"
    PRODUCTION_RESUME = "production_resume"
    PRODUCTION_STOP = "production_stop"


COMMAND_CODES: dict[Kind, int] = {Kind.IDLE: 0, Kind.PICK: 1, Kind.VERIFY: 2, Kind.PICK_MOVE: 3,
                                  Kind.PRODUCTION_START: 4, Kind.PRODUCTION_PAUSE: 5, Kind.PRODUCTION_RESUME: 6,
                                  Kind.PRODUCTION_STOP: 7}
"""The Modbus COMMAND code of each request (EtherNet/IP ``CC_Command`` uses the same codes)."""
KIND_OF_CODE: dict[int, Kind] = {code: kind for kind, code in COMMAND_CODES.items()}
MOTION: frozenset[Kind] = frozenset({Kind.PICK_MOVE, Kind.PRODUCTION_START, Kind.PRODUCTION_RESUME})
"""Requests that move the robot: only with ``plc.allow_motion``."""
URGENT: frozenset[Kind] = frozenset({Kind.PRODUCTION_PAUSE, Kind.PRODUCTION_STOP})
"""Requests never refused as busy and never queued behind another: they only slow or end a run."""
UNKNOWN_COMMAND_TEXT = ("use 0 idle, 1 pick, 2 verify, 3 pick with motion, 4..7 production start, pause, "
                        "resume, stop")


@dataclass(frozen=True)
class Request:
    """One PLC request: what (``kind``), the recipe number (pick, pick with motion, production start)
    and the parts to place (production start; 0 = until the area is empty)."""

    kind: Kind
    recipe: int = 0
    count: int = 0

    @staticmethod
    def from_command(command: int, recipe: int = 0, count: int = 0) -> Request | None:
        """The request of a Modbus/EtherNet/IP COMMAND code; None for an unknown code."""
        kind = KIND_OF_CODE.get(command)
        return None if kind is None else Request(kind, recipe, count)

    @property
    def command(self) -> int:
        return COMMAND_CODES[self.kind]

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind.value, "command": self.command}
        if self.kind in (Kind.PICK, Kind.PICK_MOVE, Kind.PRODUCTION_START):
            out["recipe"] = self.recipe
        if self.kind is Kind.PRODUCTION_START:
            out["count"] = self.count
        return out


def unknown_command(command: int) -> Outcome:
    """The answer to a COMMAND code no request has (error class 1)."""
    return failure(TEXT_UNKNOWN_COMMAND, f"unknown command code {command}: {UNKNOWN_COMMAND_TEXT}")


def answer_summary(out: Outcome) -> dict[str, Any]:
    """An outcome as ``GET /plc/status`` shows it (no poses: the count and the best pick's score)."""
    summary: dict[str, Any] = {"ok": out.ok, "error_class": out.error_class, "error_text": out.text_index,
                               "message": out.message if not out.ok else "", "picks": len(out.picks),
                               "latency_ms": round(out.latency_ms, 3)}
    if out.picked_index is not None:
        summary["picked_index"] = out.picked_index
    if out.verify is not None:
        summary["verify_passed"] = bool(out.verify.get("passed"))
    return summary


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass
class FrontEnd:
    """One front end as the engine knows it: where it listens, who is connected, what it last asked."""

    name: str
    host: str
    port: int
    motion: bool
    """Whether a client it does not authenticate could move the robot through it (pick with motion, production
    start/resume): such a front end beyond loopback needs the zone decision."""
    clients: int = 0
    requests: int = 0
    refused_busy: int = 0
    last_request: dict[str, Any] | None = None
    last_answer: dict[str, Any] | None = None
    last_outcome: Outcome | None = None
    """The last answer, kept until this front end's next request."""
    clients_of: Callable[[], int] | None = None
    """For a front end whose library keeps the connections: how many there are now (instead of ``clients``)."""
    pacer: Pacer | None = None
    """Its clients' work budget (``cellctl.plc.pacing``): frames done under it and the time they waited."""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def client_connected(self) -> None:
        with self._lock:
            self.clients += 1

    def client_disconnected(self) -> None:
        with self._lock:
            self.clients = max(0, self.clients - 1)

    def status(self) -> dict[str, Any]:
        clients = self.clients
        if self.clients_of is not None:
            try:
                clients = int(self.clients_of())
            except Exception:  # noqa: BLE001 - a count for a status page; the front end may be stopping
                clients = 0
        with self._lock:
            return {"enabled": True, "address": f"{self.host}:{self.port}", "host": self.host, "port": self.port,
                    "clients": clients, "requests": self.requests, "refused_busy": self.refused_busy,
                    "last_request": self.last_request, "last_answer": self.last_answer,
                    "paced": None if self.pacer is None else self.pacer.status()}


FRONT_ENDS = ("modbus", "opcua", "ethernet_ip", "robot_socket")
"""The front ends ``GET /plc/status`` lists, in this order (others, e.g. OPC 40100, after them)."""


class Engine:
    """The cell's PLC request engine (one per :class:`Services`: :func:`engine_for`)."""

    def __init__(self, services: Services) -> None:
        self.services = services
        self._lock = threading.Lock()
        self._running: tuple[str, Request] | None = None
        self._front_ends: dict[str, FrontEnd] = {}
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plc-request")
        self._urgent = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plc-request-urgent")
        self._closed = False

    # -- front ends ---------------------------------------------------------------------------------
    def register(self, name: str, host: str, port: int, motion: bool = True) -> FrontEnd:
        """Announce a front end listening on ``host:port``; refuses (``OSError``) a non-loopback address for a
        front end through which an unauthenticated client could move the robot (``motion``) while
        ``plc.allow_motion`` is on, without ``plc.insecure_plc_network``. Registering a name again replaces it."""
        plc = self.services.config.plc
        if motion and plc.allow_motion and not plc.insecure_plc_network and not is_loopback_host(host):
            raise OSError(f"plc.allow_motion with the PLC {name} front end on {host} (not loopback): it does not "
                          "authenticate its clients, so any client on that network could make the robot move; "
                          "turn allow_motion off, or, if the PLC network is a separate IEC 62443 zone whose "
                          "conduit admits only the PLC, record that decision with plc.insecure_plc_network: true")
        front = FrontEnd(name, host, port, motion)
        with self._lock:
            self._front_ends[name] = front
        return front

    def unregister(self, name: str) -> None:
        with self._lock:
            self._front_ends.pop(name, None)

    def front_end(self, name: str) -> FrontEnd | None:
        with self._lock:
            return self._front_ends.get(name)

    # -- requests -----------------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        with self._lock:
            return self._running is not None

    def running(self) -> tuple[str, Request] | None:
        """The front end and request running now (None: idle)."""
        with self._lock:
            return self._running

    def submit(self, front: FrontEnd, request: Request, who: str | None = None) -> Future[Outcome]:
        """Start ``request`` for ``front`` without waiting; the future's result is the answer (never an
        exception). Thread-safe; fine to call on an event loop (``asyncio.wrap_future`` the result)."""
        who = who or f"plc:{front.name}"
        with front._lock:
            front.requests += 1
            front.last_request = {**request.describe(), "at": _now(), "who": who}
            front.last_answer = None
            front.last_outcome = None
        if request.kind is Kind.IDLE:
            return self._finished(front, Outcome(True))
        urgent = request.kind in URGENT
        with self._lock:
            if self._closed:
                return self._finished(front, failure(TEXT_INTERNAL, "the PLC front ends are shutting down"))
            if not urgent and self._running is not None:
                other, what = self._running
                with front._lock:
                    front.refused_busy += 1
                return self._finished(front, failure(
                    TEXT_BUSY, f"refused: a {what.kind.value} request from the {other} front end is running; "
                               "wait until it is answered, then send again"))
            if not urgent:
                self._running = (front.name, request)
        executor = self._urgent if urgent else self._worker
        try:
            future = executor.submit(self._execute, request, who)
        except RuntimeError:  # shut down meanwhile
            self._release(urgent)
            return self._finished(front, failure(TEXT_INTERNAL, "the PLC front ends are shutting down"))
        answer: Future[Outcome] = Future()

        def done(f: Future[Outcome]) -> None:
            self._release(urgent)
            out = f.result() if not f.cancelled() and f.exception() is None else failure(
                TEXT_INTERNAL, "the request was cancelled (server shutting down)")
            self._record(front, out)
            answer.set_result(out)

        future.add_done_callback(done)
        return answer

    def run(self, front: FrontEnd, request: Request, who: str | None = None, timeout_s: float | None = None
            ) -> Outcome:
        """:meth:`submit` and wait for the answer (from a worker thread, never an event loop)."""
        return self.submit(front, request, who).result(timeout_s)

    def _release(self, urgent: bool) -> None:
        if not urgent:
            with self._lock:
                self._running = None

    def _finished(self, front: FrontEnd, out: Outcome) -> Future[Outcome]:
        self._record(front, out)
        f: Future[Outcome] = Future()
        f.set_result(out)
        return f

    def _record(self, front: FrontEnd, out: Outcome) -> None:
        with front._lock:
            front.last_outcome = out
            front.last_answer = {**answer_summary(out), "at": _now()}

    def _execute(self, request: Request, who: str) -> Outcome:
        from cellctl.plc.production import execute_production

        t0 = time.perf_counter()
        try:
            if request.kind is Kind.PICK:
                out = execute_pick(self.services, request.recipe, who)
            elif request.kind is Kind.PICK_MOVE:
                out = execute_pick(self.services, request.recipe, who, move=True)
            elif request.kind is Kind.VERIFY:
                out = execute_verify(self.services, who)
            else:
                out = execute_production(self.services, request.command, request.recipe, request.count, who)
        except Exception as exc:  # noqa: BLE001 - the request functions never raise; a bug answers 99
            log.exception("PLC request %s failed", request)
            out = failure(TEXT_INTERNAL, f"internal error: {exc}")
        if not out.latency_ms:
            out.latency_ms = (time.perf_counter() - t0) * 1e3
        return out

    # -- status and life cycle ----------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """``GET /plc/status``: every front end (disabled ones too), and the request running now."""
        with self._lock:
            fronts = dict(self._front_ends)
            running = self._running
        return status_of(self.services, fronts, running)

    def close(self) -> None:
        """Refuse new requests and join the workers (the running request finishes first)."""
        with self._lock:
            self._closed = True
        self._worker.shutdown(wait=True, cancel_futures=True)
        self._urgent.shutdown(wait=True, cancel_futures=True)


def status_of(services: Services, fronts: dict[str, FrontEnd], running: tuple[str, Request] | None
              ) -> dict[str, Any]:
    """The status of the front ends ``fronts`` (the others shown disabled, with their configured address)."""
    plc = services.config.plc
    out: dict[str, Any] = {}
    for name in (*FRONT_ENDS, *sorted(set(fronts) - set(FRONT_ENDS))):
        front = fronts.get(name)
        if front is not None:
            out[name] = front.status()
            continue
        section = getattr(plc, name, None)
        host, port = getattr(section, "host", None), getattr(section, "port", None)
        out[name] = {"enabled": False, "address": None if host is None else f"{host}:{port}", "host": host,
                     "port": port, "clients": 0, "requests": 0, "refused_busy": 0, "last_request": None,
                     "last_answer": None, "paced": None}
    return {"allow_motion": plc.allow_motion, "insecure_plc_network": plc.insecure_plc_network,
            "busy": running is not None,
            "running": None if running is None else {"front_end": running[0], **running[1].describe()},
            "front_ends": out}


def plc_status(services: Services) -> dict[str, Any]:
    """``GET /plc/status`` whether or not a front end runs (memory only)."""
    engine = existing_engine(services)
    return engine.status() if engine is not None else status_of(services, {}, None)


def engine_for(services: Services) -> Engine:
    """The service's request engine (``services.plc_engine``: made on first use)."""
    return services.plc_engine


def existing_engine(services: Services) -> Engine | None:
    """The service's request engine if one was made (memory only)."""
    engine: Engine | None = getattr(services, "_plc_engine", None)
    return engine


def forget_engine(services: Services) -> None:
    """Close the service's engine (at the end of the service, after its front ends stopped)."""
    services.close_plc_engine()
