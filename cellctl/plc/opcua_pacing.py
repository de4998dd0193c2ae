"""Pacing the OPC UA server's message processing like the other front ends' frames (``cellctl.plc.pacing``).

asyncua processes each message of a connection in that connection's task (``UaProcessor.process``),
on the OPC UA server's loop. :func:`pace` makes every connection the server admits from then on
wait for the front end's budget before a message and charge it after, with the loop thread's CPU
time (a method call awaits the pick in the engine's worker: that wait is not charged). It hooks the
list asyncua keeps of the server's connections (``BinaryServer.clients``: each new connection is
appended once its processor exists, before its first message); ``paced`` counts the messages, and
tests/plc/test_opcua_pacing.py checks that a real client's requests are paced, so an asyncua change
that bypasses the hook fails a test instead of leaving OPC UA unpaced.
"""

from __future__ import annotations

import time
from typing import Any

from cellctl.plc.pacing import Pacer


class PacedClients(list[Any]):
    """asyncua's list of a server's connections; a connection appended gets its messages paced."""

    def __init__(self, existing: list[Any], pacer: Pacer) -> None:
        super().__init__(existing)
        self.pacer = pacer
        self.paced = 0
        """Messages processed under the pacer."""

    def append(self, protocol: Any) -> None:
        processor = getattr(protocol, "processor", None)
        if processor is not None and not getattr(processor, "cellctl_paced", False):
            process = processor.process

            async def paced(header: Any, body: Any) -> Any:
                t0 = await self.pacer.wait()
                try:
                    return await process(header, body)
                finally:
                    self.pacer.done(t0)
                    self.paced += 1

            processor.process = paced
            processor.cellctl_paced = True
        super().append(protocol)


def pace(server: Any) -> PacedClients | None:
    """Pace the connections a started asyncua ``Server`` admits from now on; None if it has no binary server."""
    bserver = getattr(server, "bserver", None)
    if bserver is None or not isinstance(getattr(bserver, "clients", None), list):
        return None
    clients = PacedClients(bserver.clients, Pacer(clock=time.thread_time))
    bserver.clients = clients
    return clients
