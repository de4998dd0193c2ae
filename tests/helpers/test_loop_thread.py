"""drivers.loop_thread: an asyncio server in its own thread, with start errors raised in the caller."""

from __future__ import annotations

import asyncio
import socket

import pytest

from drivers.loop_thread import LoopNotRunning, LoopThread
from tests.conftest import free_port


class EchoServer:
    def __init__(self, port: int) -> None:
        self.port = port
        self.server: asyncio.Server | None = None

    async def serve(self) -> None:
        async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            writer.write(await reader.readline())
            await writer.drain()
            writer.close()

        self.server = await asyncio.start_server(echo, "127.0.0.1", self.port)

    async def shutdown(self) -> None:
        if self.server is not None:
            self.server.close()
            await self.server.wait_closed()


def _echo(port: int, text: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(text)
        return s.makefile("rb").readline()


def test_serves_calls_and_stops() -> None:
    port = free_port()
    echo, thread = EchoServer(port), LoopThread("echo-test")
    thread.start(echo.serve)
    try:
        assert thread.running
        assert _echo(port, b"hello\n") == b"hello\n"

        async def add() -> int:
            await asyncio.sleep(0)
            return 2 + 3

        assert thread.call(add) == 5
    finally:
        thread.stop(echo.shutdown)
    assert not thread.running
    with pytest.raises(OSError):
        _echo(port, b"gone\n")
    thread.stop(echo.shutdown)  # twice is fine


def test_a_failed_start_raises_in_the_callers_thread() -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        thread = LoopThread("echo-taken")
        with pytest.raises(OSError) as err:
            thread.start(EchoServer(taken.getsockname()[1]).serve)
        assert "address already in use" in str(err.value).lower() or err.value.errno is not None
        assert not thread.running
    finally:
        taken.close()


def test_a_start_that_never_returns_times_out() -> None:
    never = asyncio.Event()
    thread = LoopThread("never")

    async def serve() -> None:
        await asyncio.wait_for(never.wait(), 5.0)

    with pytest.raises(TimeoutError, match="never did not start"):
        thread.start(serve, timeout_s=0.2)


def test_call_before_start_is_a_typed_error() -> None:
    async def nothing() -> None:
        return None

    with pytest.raises(LoopNotRunning, match="not running"):
        LoopThread("idle").call(nothing)
    LoopThread("idle").stop()  # before start: nothing to do
