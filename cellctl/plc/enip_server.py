"""The EtherNet/IP tag server for Rockwell PLCs: CIP explicit messaging, Logix-style tags (cpppo).

With ``plc.ethernet_ip.enabled`` the service answers on ``plc.ethernet_ip.host:port`` (default
127.0.0.1:44818) as a Logix controller would to "CIP Data Table Read/Write" MSG instructions and
to Read/Write Tag services (unconnected, or connected after a Forward Open). The tags and their
handshake: ``cellctl.plc.enip_tags`` and docs/plc-ethernet-ip.md.

The protocol (the encapsulation parser, the UCMM, the Connection Manager, the Logix Read/Write Tag
[Fragmented] services) is cpppo's; the network side is ours, on an asyncio loop in a thread this
server owns: each encapsulation frame is read whole (24-byte header, then its length, at most
``MAX_FRAME`` bytes), parsed and answered by cpppo on the loop, so the tags change only there. A
frame cpppo cannot parse, an over-long frame, a connection over ``max_clients`` or silent for
``idle_timeout_s`` is closed, with one rate-limited log line and never a traceback. The frames'
work is paced (``cellctl.plc.pacing``): cpppo's parser is pure Python, and a client polling as fast
as it is answered must not take the interpreter from Stop.

cpppo keeps its CIP objects (identity, message router, tags) in one registry per process, so one
EtherNet/IP server runs per process (a second start is refused).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import threading
from typing import Any

from cellctl.config import EthernetIpServerConfig, is_loopback_host
from cellctl.plc.engine import Engine, FrontEnd, Request, engine_for
from cellctl.plc.enip_tags import TAGS, RefusedWrite, TagImage, TagSpec
from cellctl.plc.pacing import Pacer
from cellctl.plc.quiet_log import client_mistake, quiet
from cellctl.plc.requests import Outcome
from cellctl.services import Services
from drivers.loop_thread import LoopThread

log = logging.getLogger(__name__)

HEADER = 24
MAX_FRAME = 4096
"""Largest encapsulation frame taken (header + data); a Logix MSG of 64 REALs is about 330 bytes."""
_ONE_SERVER = threading.Lock()
_ATTRIBUTES: dict[str, Any] = {}
"""The tags' cpppo attributes, by name (one set per process; each server points them at its image)."""


def _cpppo() -> Any:
    """cpppo's modules, imported on first use (2.5 s; its loggers quietened first)."""
    for name in ("enip", "cpppo", "parser", "network"):
        logging.getLogger(name).setLevel(max(logging.WARNING, logging.getLogger(name).level))
    import cpppo
    from cpppo.server.enip import device, logix, parser

    for name in ("enip", "cpppo", "parser", "network"):
        quiet(name)  # after the import: its loggers exist now
    return cpppo, device, logix, parser


def _attribute_class(device: Any) -> Any:
    class TagAttribute(device.Attribute):  # type: ignore[misc,name-defined]
        """A cpppo Attribute whose value lives in the :class:`TagImage` (read and written on the loop)."""

        def __init__(self, spec: TagSpec, image: TagImage, type_cls: Any) -> None:
            default: Any = [0] * spec.count if spec.count > 1 else 0
            if spec.cip_type == "REAL":
                default = [0.0] * spec.count
            if spec.cip_type == "STRING":
                default = ""
            super().__init__(spec.name, type_cls, default=default)
            self.spec, self.image = spec, image

        @property
        def value(self) -> Any:
            return self.image.read(self.spec.name)

        @value.setter
        def value(self, v: Any) -> None:
            self.image.write(self.spec.name, int(v) if self.spec.cip_type == "DINT" else v)

        def __setitem__(self, key: Any, value: Any) -> None:
            if self.spec.count > 1:
                raise RefusedWrite(f"{self.spec.name} is read-only")
            if isinstance(key, slice):
                value = next(iter(value))
            self.value = value

    return TagAttribute


class EthernetIpServer:
    """The PLC's EtherNet/IP tag server for one cell; ``start()`` listens, ``stop()`` ends it."""

    def __init__(self, services: Services, config: EthernetIpServerConfig, engine: Engine | None = None) -> None:
        self.services, self.config = services, config
        self.engine = engine or engine_for(services)
        self.image = TagImage(services, self._submit)
        self._thread = LoopThread(f"plc-enip-{config.port}")
        self._server: asyncio.Server | None = None
        self._front: FrontEnd | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._kwds: dict[str, Any] = {}
        self._mods: Any = None
        self._pacer = Pacer()
        self.clients = 0
        self.closed_bad = 0
        self.address: tuple[str, int] = (config.host, config.port)

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> EthernetIpServer:
        if not _ONE_SERVER.acquire(blocking=False):
            raise OSError("an EtherNet/IP server already runs in this process (cpppo keeps one tag registry)")
        try:
            self._mods = _cpppo()
            self._kwds = self._setup_tags()
            self._front = self.engine.register("ethernet_ip", self.config.host, self.config.port)
            self._thread.start(self._listen)
        except BaseException:
            self.engine.unregister("ethernet_ip")
            _ONE_SERVER.release()
            raise
        log.info("PLC EtherNet/IP tag server on %s:%d (%d tags)", self.config.host, self.address[1], len(TAGS))
        if not is_loopback_host(self.config.host):
            log.warning("PLC EtherNet/IP server on %s: EtherNet/IP has no authentication; keep this address on the "
                        "PLC's network only", self.config.host)
        return self

    def stop(self) -> None:
        async def shutdown() -> None:
            if self._server is not None:
                self._server.close()
            for task in list(self._tasks):
                task.cancel()
            if self._tasks:
                await asyncio.gather(*self._tasks, return_exceptions=True)
            if self._server is not None:
                await self._server.wait_closed()

        try:
            self._thread.stop(shutdown)
        finally:
            self.engine.unregister("ethernet_ip")
            if _ONE_SERVER.locked():
                _ONE_SERVER.release()

    def _setup_tags(self) -> dict[str, Any]:
        """Point the process's tag attributes at this server's image (made and registered with cpppo once:
        cpppo keeps the first attribute of a tag name for the life of the process)."""
        cpppo, device, logix, parser = self._mods
        if not _ATTRIBUTES:
            attr_cls = _attribute_class(device)
            tags = cpppo.dotdict()
            for spec in TAGS:
                entry = cpppo.dotdict()
                entry.attribute = _ATTRIBUTES[spec.name] = attr_cls(spec, self.image, getattr(parser, spec.cip_type))
                entry.path = None
                entry.error = 0x00
                dict.__setitem__(tags, spec.name, entry)
            logix.setup(tags=tags)  # creates the tags in cpppo's registry
        for attribute in _ATTRIBUTES.values():
            attribute.image = self.image
        # ``logix.process`` re-checks every tag it is given on every frame (8 % of a frame's time): the tags
        # are set up once, here, and each frame is processed without them.
        return {}

    async def _listen(self) -> None:
        try:
            self._server = await asyncio.start_server(self._serve, self.config.host, self.config.port,
                                                      reuse_address=True)
        except OSError as exc:
            raise OSError(f"PLC EtherNet/IP server cannot listen on {self.config.host}:{self.config.port} "
                          f"({exc.strerror or exc}); free the port or change plc.ethernet_ip.port") from None
        sock = self._server.sockets[0].getsockname()
        self.address = (str(sock[0]), int(sock[1]))

    # -- requests -----------------------------------------------------------------------------------
    def _submit(self, request: Request, answer: Any) -> None:
        """Start a request through the engine; ``answer(outcome)`` runs on the loop when it is done."""
        assert self._front is not None
        future = self.engine.submit(self._front, request, "plc:ethernet_ip")
        if future.done():
            answer(future.result())
            return
        loop = asyncio.get_running_loop()

        def done(f: Any) -> None:
            out: Outcome = f.result()
            loop.call_soon_threadsafe(answer, out)

        future.add_done_callback(done)

    # -- connections --------------------------------------------------------------------------------
    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        peer = writer.get_extra_info("peername")
        addr = (str(peer[0]), int(peer[1])) if peer else ("?", 0)
        if self.clients >= self.config.max_clients:
            client_mistake(log, "EtherNet/IP connections over the cap", "PLC EtherNet/IP: refused a connection from "
                           "%s (%d at once: plc.ethernet_ip.max_clients)", addr[0], self.clients)
            writer.close()
            return
        if task is not None:
            self._tasks.add(task)
        self.clients += 1
        if self._front is not None:
            self._front.clients = self.clients
        cpppo, _device, _logix, parser = self._mods
        try:
            with parser.enip_machine(name=f"enip_{addr[1]}", context="enip") as machine:
                while True:
                    frame = await self._read_frame(reader, addr)
                    if frame is None:
                        break
                    t0 = await self._pacer.wait()
                    reply, keep = self._answer(cpppo, parser, machine, frame, addr)
                    self._pacer.done(t0)
                    if reply:
                        writer.write(reply)
                        await writer.drain()
                    if not keep:
                        break
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self.clients -= 1
            if self._front is not None:
                self._front.clients = self.clients
            if task is not None:
                self._tasks.discard(task)
            with contextlib.suppress(Exception):
                self._mods[2].process(addr, data=cpppo.dotdict(), **self._kwds)  # ends the CIP session
            writer.close()

    async def _read_frame(self, reader: asyncio.StreamReader, addr: tuple[str, int]) -> bytes | None:
        """One whole encapsulation frame; None at the end, when idle too long or when it is too long."""
        try:
            header = await asyncio.wait_for(reader.readexactly(HEADER), self.config.idle_timeout_s)
        except TimeoutError:
            client_mistake(log, "idle EtherNet/IP connections", "PLC EtherNet/IP: closed the connection from %s: "
                           "silent for %.0f s (plc.ethernet_ip.idle_timeout_s)", addr[0], self.config.idle_timeout_s)
            return None
        except asyncio.IncompleteReadError:
            return None
        (length,) = struct.unpack_from("<H", header, 2)
        if HEADER + length > MAX_FRAME:
            self.closed_bad += 1
            client_mistake(log, "over-long EtherNet/IP frames", "PLC EtherNet/IP: closed the connection from %s: a "
                           "frame of %d bytes (at most %d)", addr[0], HEADER + length, MAX_FRAME)
            return None
        body = await asyncio.wait_for(reader.readexactly(length), self.config.idle_timeout_s) if length else b""
        return header + body

    def _answer(self, cpppo: Any, parser: Any, machine: Any, frame: bytes, addr: tuple[str, int]
                ) -> tuple[bytes | None, bool]:
        """cpppo's answer to one frame, and whether to keep the connection."""
        data = cpppo.dotdict()
        source = cpppo.rememberable()
        source.chain(frame)
        try:
            with contextlib.closing(machine.run(path="request", source=source, data=data)) as engine:
                for _m, state in engine:
                    if state is None and source.peek() is None:
                        raise ValueError("an incomplete encapsulation frame")
            if "request.enip" not in data:
                raise ValueError("not an EtherNet/IP encapsulation frame")
            keep = bool(self._mods[2].process(addr, data=data, **self._kwds))
            if not keep:
                return None, False
            reply = parser.enip_encode(data.response.enip)
            return bytes(reply), not data.response.enip.status
        except Exception as exc:  # noqa: BLE001 - a client's garbage closes its connection, nothing more
            self.closed_bad += 1
            text = str(exc).strip().splitlines()
            client_mistake(log, "bad EtherNet/IP frames", "PLC EtherNet/IP: closed the connection from %s: a frame "
                           "cpppo cannot take (%s)", addr[0], (text[0] if text else type(exc).__name__)[:120])
            return None, False
