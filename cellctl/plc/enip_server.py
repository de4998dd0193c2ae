"""The EtherNet/IP tag server for Rockwell PLCs: CIP explicit messaging, Logix-style tags (cpppo).

With ``plc.ethernet_ip.enabled`` the service answers on ``plc.ethernet_ip.host:port`` (default
127.0.0.1:44818) as a Logix controller would to "CIP Data Table Read/Write" MSG instructions and
to Read/Write Tag services (unconnected, or connected after a Forward Open). The tags and their
handshake: ``cellctl.plc.enip_tags`` and docs/plc-ethernet-ip.md.

The frames a PLC sends over and over (Read Tag / Write Tag of our tags, connected or unconnected)
are answered by a struct-level fast path (``cellctl.plc.enip_fast``, byte for byte as cpppo would,
a thousand times faster); everything else (Register Session, Forward Open/Close, other services,
unknown tags, malformed frames) is cpppo's: the encapsulation parser, the UCMM, the Connection
Manager, the Logix Read/Write Tag [Fragmented] services. The network side is ours
(``cellctl.plc.stream_server``: an asyncio loop in a thread this server owns): each encapsulation
frame is read whole (24-byte header, then its length, at most ``MAX_FRAME`` bytes) and answered on
the loop, so the tags change only there. A frame cpppo cannot parse, an over-long frame, a
connection over ``max_clients`` or silent for ``idle_timeout_s`` is closed, with one rate-limited
log line and never a traceback. The frames' work is paced (``cellctl.plc.pacing``): a client
polling as fast as it is answered must not take the interpreter from Stop.

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

from cellctl.config_listeners import EthernetIpServerConfig, is_loopback_host
from cellctl.errors import CellctlError
from cellctl.plc.engine import Engine, Request
from cellctl.plc.enip_fast import FastPath
from cellctl.plc.enip_tags import TAGS, RefusedWrite, TagImage, TagSpec
from cellctl.plc.quiet_log import client_mistake, quiet
from cellctl.plc.requests import Outcome
from cellctl.plc.stream_server import StreamServer
from cellctl.services import Services
from drivers.loop_thread import LoopNotRunning

log = logging.getLogger(__name__)

HEADER = 24
MAX_FRAME = 4096
"""Largest encapsulation frame taken (header + data); a Logix MSG of 64 REALs is about 330 bytes."""
_ONE_SERVER = threading.Lock()
_ATTRIBUTES: dict[str, Any] = {}
"""The tags' cpppo attributes, by name (one set per process; each server points them at its image)."""


class EthernetIpUnavailable(CellctlError, RuntimeError):
    """The EtherNet/IP front end is configured but its protocol library (cpppo, an extra) is missing."""


def _cpppo() -> Any:
    """cpppo's modules, imported on first use (2.5 s; its loggers quietened first)."""
    for name in ("enip", "cpppo", "parser", "network"):
        logging.getLogger(name).setLevel(max(logging.WARNING, logging.getLogger(name).level))
    try:
        import cpppo
        from cpppo.server.enip import device, logix, parser
    except ImportError as exc:
        raise EthernetIpUnavailable(
            f"plc.ethernet_ip is enabled but cpppo is not installed ({exc}): install the extra with "
            "`pip install 'cellctl[ethernet-ip]'` (deploy/install.sh --ethernet-ip), or disable plc.ethernet_ip"
        ) from exc

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


class EthernetIpServer(StreamServer):
    """The PLC's EtherNet/IP tag server for one cell; ``start()`` listens, ``stop()`` ends it (``StreamServer``)."""

    name, setting, title = "ethernet_ip", "plc.ethernet_ip", "PLC EtherNet/IP server"
    config: EthernetIpServerConfig

    def __init__(self, services: Services, config: EthernetIpServerConfig, engine: Engine | None = None) -> None:
        super().__init__(services, config, engine)
        self.image = TagImage(services, self._submit)
        self._kwds: dict[str, Any] = {}
        self._mods: Any = None
        self.closed_bad = 0
        self.fast_frames = 0
        """Frames the struct-level fast path answered (``cellctl.plc.enip_fast``); the others went to cpppo."""
        self.cpppo_frames = 0

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> EthernetIpServer:
        if not _ONE_SERVER.acquire(blocking=False):
            raise OSError("an EtherNet/IP server already runs in this process (cpppo keeps one tag registry)")
        try:
            self._mods = _cpppo()
            self._kwds = self._setup_tags()
            super().start()
        except BaseException:
            _ONE_SERVER.release()
            raise
        log.info("PLC EtherNet/IP tag server on %s:%d (%d tags)", self.config.host, self.address[1], len(TAGS))
        if not is_loopback_host(self.config.host):
            log.warning("PLC EtherNet/IP server on %s: EtherNet/IP has no authentication; keep this address on the "
                        "PLC's network only", self.config.host)
        return self

    def stop(self) -> None:
        try:
            super().stop()
        finally:
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

    # -- requests -----------------------------------------------------------------------------------
    def _submit(self, request: Request, answer: Any) -> None:
        """Start a request through the engine; ``answer(outcome)`` runs on the loop when it is done."""
        if self._front is None:
            raise LoopNotRunning("the EtherNet/IP server is not started: start() registers its front end")
        future = self.engine.submit(self._front, request, "plc:ethernet_ip")
        if future.done():
            answer(future.result())
            return
        loop = asyncio.get_running_loop()

        def done(f: Any) -> None:
            out: Outcome = f.result()
            loop.call_soon_threadsafe(answer, out)

        future.add_done_callback(done)

    # -- connections (StreamServer) -----------------------------------------------------------------
    async def serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                           addr: tuple[str, int]) -> None:
        cpppo, _device, logix, parser = self._mods
        fast = FastPath(self.image)
        try:
            with parser.enip_machine(name=f"enip_{addr[1]}", context="enip") as machine:
                while True:
                    frame = await self._read_frame(reader, addr)
                    if frame is None:
                        return
                    t0 = await self.pacer.wait()
                    reply, keep = (fast.answer(frame) if FastPath.enabled else None), True
                    if reply is not None:
                        self.fast_frames += 1
                    else:
                        self.cpppo_frames += 1
                        reply, keep = self._answer(cpppo, parser, machine, frame, addr)
                        fast.learn(frame, reply)
                    self.pacer.done(t0)
                    if reply:
                        writer.write(reply)
                        await writer.drain()
                    if not keep:
                        return
        finally:
            with contextlib.suppress(Exception):
                logix.process(addr, data=cpppo.dotdict(), **self._kwds)  # ends the CIP session

    async def _read_frame(self, reader: asyncio.StreamReader, addr: tuple[str, int]) -> bytes | None:
        """One whole encapsulation frame; None at the end, when idle too long or when it is too long."""
        try:
            header = await self.within_idle(reader.readexactly(HEADER), addr)
        except asyncio.IncompleteReadError:
            return None
        if header is None:
            return None
        (length,) = struct.unpack_from("<H", header, 2)
        if HEADER + length > MAX_FRAME:
            self.closed_bad += 1
            client_mistake(log, "over-long EtherNet/IP frames", "PLC EtherNet/IP: closed the connection from %s: a "
                           "frame of %d bytes (at most %d)", addr[0], HEADER + length, MAX_FRAME)
            return None
        body = await self.within_idle(reader.readexactly(length), addr) if length else b""
        return None if body is None else header + body

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
