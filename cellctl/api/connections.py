"""HTTP connections no client can use up: a header deadline, per-address and total caps, descriptors in reserve.

uvicorn times out an idle kept-alive connection, but never a connection whose request headers are
still arriving: 1,100 clients each sending one header byte now and then held every descriptor of
the process, and a new Stop could not connect. The service's HTTP protocol
(:func:`guarded_protocol`, uvicorn's h11 protocol with three additions) therefore

- closes a connection whose request headers have not arrived whole within ``http.header_timeout_s``
  (10 s) of its opening, or of the previous answer on a kept-alive connection;
- keeps at most ``http.max_connections_per_address`` (256) connections per client address and at
  most :func:`connection_cap` in all. A new connection over a cap does not wait and is not refused
  while an *idle* one exists (headers still arriving, or kept alive between requests): the oldest
  idle connection (of that address, for the per-address cap) is closed to admit it. Only when
  every connection is busy being answered is the new one closed. A Stop sends its headers at
  once, so it is never idle and never the oldest: whatever else holds connections, it gets in;
- keeps :data:`FD_RESERVE` descriptors of the process's open-files limit (``RLIMIT_NOFILE``) out of
  the cap's reach, for what the answers themselves need (the store, devices, the PLC servers, the
  log). ``cellctl serve`` raises its soft limit towards the hard one at start
  (:func:`raise_open_files_limit`); the systemd unit sets ``LimitNOFILE``. The listening backlog
  is :data:`ACCEPT_BACKLOG` (256), so a burst of connections accepted at once stays within the reserve.

Closed connections are counted (:class:`ConnectionGuard` ``.closed``), never logged one by one.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, ClassVar

from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

FD_RESERVE = 512
"""Descriptors of the open-files limit never given to HTTP connections (store, devices, PLC, logs)."""
WANTED_OPEN_FILES = 65_536
"""The soft open-files limit ``cellctl serve`` asks for at start (at most the hard limit)."""
MIN_CONNECTIONS = 16
ACCEPT_BACKLOG = FD_RESERVE // 2
"""The listening socket's backlog (uvicorn's default is 2,048). asyncio accepts up to this many
connections per wake-up, each a descriptor, before the protocol can close one over the cap: the
backlog bounds that overshoot to half the reserve (at 1,024 descriptors a 2,048 backlog ran the
process out of them, and ``accept()`` then paused for a second)."""


def open_files_limit() -> tuple[int, int]:
    """The process's (soft, hard) ``RLIMIT_NOFILE``."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    return int(soft), int(hard)


def raise_open_files_limit(wanted: int = WANTED_OPEN_FILES) -> int:
    """Raise the soft open-files limit towards ``wanted`` (never above the hard limit, never lowered);
    answers the soft limit in force."""
    soft, hard = open_files_limit()
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:  # a container may forbid it: the cap follows the old limit
            log.warning("cannot raise the open-files limit from %d to %d (%s); HTTP connections are capped "
                        "accordingly", soft, target, exc)
    return soft


def connection_cap(configured: int, soft_limit: int | None = None) -> int:
    """The HTTP connections allowed: ``configured``, lowered to keep :data:`FD_RESERVE` descriptors
    (or a quarter of a small limit) free; at least :data:`MIN_CONNECTIONS`."""
    soft = open_files_limit()[0] if soft_limit is None else soft_limit
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return max(MIN_CONNECTIONS, configured)
    reserve = max(FD_RESERVE, soft // 4) if soft < 4 * FD_RESERVE else FD_RESERVE
    return max(MIN_CONNECTIONS, min(configured, soft - reserve))


@dataclass
class GuardCounts:
    """How many connections the guard closed, by reason (never logged one by one)."""

    header_timeout: int = 0
    evicted: int = 0
    refused: int = 0


@dataclass
class ConnectionGuard:
    """The open connections of one server, oldest first, per address and in all."""

    max_connections: int
    max_per_address: int
    header_timeout_s: float
    closed: GuardCounts = field(default_factory=GuardCounts)
    _all: OrderedDict[int, Any] = field(default_factory=OrderedDict)
    _by_address: dict[str, OrderedDict[int, Any]] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self._all)

    def admit(self, conn: Any, address: str) -> bool:
        """Add ``conn``; over a cap, close the oldest idle connection first. False: every connection
        is busy, ``conn`` must be closed."""
        mine = self._by_address.get(address)
        if mine is not None and len(mine) >= self.max_per_address and not self._evict(mine):
            self.closed.refused += 1
            return False
        if len(self._all) >= self.max_connections and not self._evict(self._all):
            self.closed.refused += 1
            return False
        self._all[id(conn)] = conn
        self._by_address.setdefault(address, OrderedDict())[id(conn)] = conn
        return True

    def release(self, conn: Any, address: str) -> None:
        self._all.pop(id(conn), None)
        mine = self._by_address.get(address)
        if mine is not None:
            mine.pop(id(conn), None)
            if not mine:
                del self._by_address[address]

    def _evict(self, conns: OrderedDict[int, Any]) -> bool:
        for conn in conns.values():
            if conn.idle():
                conn.close_now()
                self.release(conn, conn.address)  # (the loop ends here: changing the dict is safe)
                self.closed.evicted += 1
                return True
        return False


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with the header deadline and the connection caps of a :class:`ConnectionGuard`."""

    guard: ClassVar[ConnectionGuard]

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_timer: asyncio.TimerHandle | None = None
        self._awaited: object = None
        self._admitted = False
        client = self.client
        self.address = str(client[0]) if client else "?"
        if not self.guard.admit(self, self.address):
            self.close_now()
            return
        self._admitted = True
        self._arm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._admitted:
            self.guard.release(self, self.address)
            self._admitted = False
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().connection_lost(exc)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_deadline()  # the next request's headers have the same deadline

    def idle(self) -> bool:
        """True while no request is being answered (headers still arriving, or kept alive between requests)."""
        return self.cycle is None or self.cycle.response_complete

    def close_now(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        self._admitted = False
        if not self.transport.is_closing():
            self.transport.close()

    def _arm_header_deadline(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
        self._awaited = self.cycle  # a new request makes a new cycle
        self._header_timer = self.loop.call_later(self.guard.header_timeout_s, self._header_deadline)

    def _header_deadline(self) -> None:
        self._header_timer = None
        if self.cycle is self._awaited and not self.transport.is_closing():
            self.guard.closed.header_timeout += 1
            if self._admitted:
                self.guard.release(self, self.address)
                self._admitted = False
            self.transport.close()


def guarded_protocol(http: Any, soft_limit: int | None = None) -> type[GuardedH11Protocol]:
    """The HTTP protocol class for uvicorn (``http=``) with the limits of ``http`` (the config's section)."""
    guard = ConnectionGuard(connection_cap(int(http.max_connections), soft_limit),
                            int(http.max_connections_per_address), float(http.header_timeout_s))
    return type("CellctlHttpProtocol", (GuardedH11Protocol,), {"guard": guard})
