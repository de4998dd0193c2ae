"""One life cycle for the PLC front ends that are plain asyncio TCP servers (EtherNet/IP, robot socket).

:class:`StreamServer` owns a :class:`~drivers.loop_thread.LoopThread` (an event loop in a thread it
starts and joins) and does what every such front end needs the same way: register with the request
engine, bind (a taken port is a clear error naming the setting to change), admit at most
``config.max_clients`` connections at once (the others are refused: :meth:`refuse`), close a
connection silent for ``config.idle_timeout_s`` (:meth:`within_idle`), count and log a client's
mistakes with one rate-limited line and never a traceback, and on ``stop()`` close the listener,
cancel every connection, join the thread and unregister. A subclass says what one connection does
(:meth:`serve_client`) and how to refuse one over the cap.

The protocol work of each connection is paced (``self.pacer``, ``cellctl.plc.pacing``): a client
polling as fast as it is answered must not take the interpreter from Stop. Only the front end's own
work is counted (``t0 = await pacer.wait()`` ... ``pacer.done(t0)`` around the parsing and the answer),
never the time a request waits for the engine.

(The Modbus server is pymodbus's own asyncio server, with its own connection objects; it shares
``LoopThread`` and the pacing, not this class.)
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable
from typing import Any, Protocol, TypeVar

from cellctl.plc.engine import Engine, FrontEnd, engine_for
from cellctl.plc.pacing import Pacer
from cellctl.plc.quiet_log import client_mistake
from cellctl.services import Services
from drivers.loop_thread import LoopThread

log = logging.getLogger(__name__)
T = TypeVar("T")


class StreamConfig(Protocol):
    """The settings a stream front end reads (``plc.ethernet_ip``, ``plc.robot_socket``)."""

    host: str
    port: int
    max_clients: int
    idle_timeout_s: float


class StreamServer:
    """An asyncio TCP front end on its own loop thread; ``start()`` listens, ``stop()`` ends and joins it."""

    name = "stream"
    """The front end's name for the request engine and ``GET /plc/status`` (``ethernet_ip``, ...)."""
    setting = "plc.stream"
    """Its configuration section, named in the errors and log lines."""
    title = "PLC stream server"
    """How the log lines call it."""
    motion = True
    """Whether its requests may move the robot (the IEC 62443 zone key for a non-loopback address)."""
    line_limit = 2**16
    """The stream reader's buffer limit (a line-based protocol sets its longest line here)."""

    def __init__(self, services: Services, config: StreamConfig, engine: Engine | None = None) -> None:
        self.services, self.config = services, config
        self.engine = engine or engine_for(services)
        self._thread = LoopThread(f"plc-{self.name.replace('_', '-')}-{config.port}")
        self._server: asyncio.Server | None = None
        self._front: FrontEnd | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self.pacer = Pacer()
        self.clients = 0
        self.refused_clients = 0
        self.address: tuple[str, int] = (config.host, config.port)

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> StreamServer:
        """Register with the engine and listen; raises (and leaves nothing registered) when it cannot."""
        self._front = self.engine.register(self.name, self.config.host, self.config.port, motion=self.motion)
        self._front.pacer = self.pacer
        try:
            self._thread.start(self._listen)
        except BaseException:
            self.engine.unregister(self.name)
            raise
        return self

    def stop(self) -> None:
        """Close the listener and every connection, join the loop thread, unregister. Safe to call twice."""

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
            self.engine.unregister(self.name)

    async def _listen(self) -> None:
        try:
            self._server = await asyncio.start_server(self._connection, self.config.host, self.config.port,
                                                      reuse_address=True, limit=self.line_limit)
        except OSError as exc:
            raise OSError(f"{self.title} cannot listen on {self.config.host}:{self.config.port} "
                          f"({exc.strerror or exc}); free the port or change {self.setting}.port") from None
        sock = self._server.sockets[0].getsockname()
        self.address = (str(sock[0]), int(sock[1]))

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        return self._thread.loop

    # -- connections (on the loop) ------------------------------------------------------------------
    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        peer = writer.get_extra_info("peername")
        addr = (str(peer[0]), int(peer[1])) if peer else ("?", 0)
        if self.clients >= self.config.max_clients:
            self.refused_clients += 1
            client_mistake(log, f"{self.name} connections over the cap", "%s: refused a connection from %s (%d at "
                           "once: %s.max_clients)", self.title, addr[0], self.clients, self.setting)
            with contextlib.suppress(ConnectionError, asyncio.CancelledError):
                await self.refuse(writer)
            writer.close()
            return
        if task is not None:
            self._tasks.add(task)
        self._count(+1)
        try:
            await self.serve_client(reader, writer, addr)
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.CancelledError):
            pass  # the client left, or the server stops: nothing to answer
        finally:
            self._count(-1)
            if task is not None:
                self._tasks.discard(task)
            writer.close()

    def _count(self, step: int) -> None:
        self.clients += step
        if self._front is not None:
            self._front.clients = self.clients

    async def within_idle(self, read: Awaitable[T], addr: tuple[str, int]) -> T | None:
        """``await read`` unless the client stays silent for ``idle_timeout_s`` (then None, logged once)."""
        try:
            return await asyncio.wait_for(read, self.config.idle_timeout_s)
        except TimeoutError:
            client_mistake(log, f"idle {self.name} connections", "%s: closed the connection from %s: silent for "
                           "%.0f s (%s.idle_timeout_s)", self.title, addr[0], self.config.idle_timeout_s,
                           self.setting)
            return None

    @staticmethod
    async def send_and_close(writer: asyncio.StreamWriter, data: bytes, timeout_s: float = 2.0) -> None:
        """Send a last answer (bounded wait for a client that does not read), then close."""
        try:
            writer.write(data)
            await asyncio.wait_for(writer.drain(), timeout_s)
        except (ConnectionError, TimeoutError):
            pass
        writer.close()

    # -- what a subclass says -----------------------------------------------------------------------
    async def refuse(self, writer: asyncio.StreamWriter) -> None:
        """What a connection over ``max_clients`` gets before it is closed (nothing by default)."""

    async def serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                           addr: tuple[str, int]) -> None:
        """One admitted connection until it ends (return, or raise ConnectionError / IncompleteReadError)."""
        raise NotImplementedError
