"""A simulated LED light controller on a serial port, the peer of ``kind: serial_light``.

ASCII protocol (one command per line, ``\\r`` or ``\\n`` terminated; replies end with ``\\r\\n``):

============================  ===================================================
``VER?``                      ``LIGHTSIM 1.0 CH=<n>``
``SET <ch> <0-255>``          ``OK`` (channel ``ch`` at that intensity; 0 = off)
``GET <ch>``                  ``<ch> <intensity>``
``STROBE <ch> <us>``          ``OK`` (one pulse of ``us`` microseconds, 1..100000)
``CNT? <ch>``                 ``<ch> <number of strobes so far>``
anything else                 ``ERR <code> <text>`` (1 unknown command, 2 bad channel, 3 bad value)
============================  ===================================================

Run it on one end of a pseudo-terminal pair (``socat -d -d pty,raw,echo=0,link=/tmp/light-a
pty,raw,echo=0,link=/tmp/light-b``): ``python -m drivers.peers.serial_light --port /tmp/light-b``.
``--garbage`` makes it answer every command with bytes that follow no protocol (for fault tests).
"""

from __future__ import annotations

import argparse
import signal
import threading

import serial


class LightControllerSim:
    """The controller's state and its command interpreter."""

    def __init__(self, channels: int = 4) -> None:
        self.channels = channels
        self.intensity = [0] * channels
        self.strobes = [0] * channels

    def reply(self, line: str) -> str:
        parts = line.strip().split()
        if not parts:
            return ""
        cmd, args = parts[0].upper(), parts[1:]
        if cmd == "VER?":
            return f"LIGHTSIM 1.0 CH={self.channels}"
        if cmd in ("SET", "GET", "STROBE", "CNT?"):
            if not args or not args[0].isdigit() or not 0 <= int(args[0]) < self.channels:
                return f"ERR 2 channel must be 0..{self.channels - 1}"
            ch = int(args[0])
            if cmd == "GET":
                return f"{ch} {self.intensity[ch]}"
            if cmd == "CNT?":
                return f"{ch} {self.strobes[ch]}"
            if len(args) != 2 or not args[1].isdigit():
                return "ERR 3 value must be a whole number"
            value = int(args[1])
            if cmd == "SET":
                if not 0 <= value <= 255:
                    return "ERR 3 intensity must be 0..255"
                self.intensity[ch] = value
                return "OK"
            if not 1 <= value <= 100_000:
                return "ERR 3 strobe must be 1..100000 us"
            self.strobes[ch] += 1
            return "OK"
        return f"ERR 1 unknown command {parts[0]}"


def serve(
    port: str, channels: int = 4, baudrate: int = 115200, garbage: bool = False, stop: threading.Event | None = None
) -> None:
    """Answer commands on ``port`` until ``stop`` is set (or SIGTERM/SIGINT when run as a program)."""
    sim = LightControllerSim(channels)
    stop = stop or threading.Event()
    with serial.Serial(port, baudrate=baudrate, timeout=0.1) as ser:
        print(f"light controller simulator ready on {port}", flush=True)
        buf = b""
        while not stop.is_set():
            chunk = ser.read(256)
            if not chunk:
                continue
            buf += chunk
            while True:
                cut = min((i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0), default=-1)
                if cut < 0:
                    break
                line, buf = buf[:cut], buf[cut + 1 :]
                if not line.strip():
                    continue
                if garbage:
                    ser.write(b"\xfe\x00#?!\xff garbage\r\n")
                    continue
                ser.write(sim.reply(line.decode("ascii", "replace")).encode() + b"\r\n")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Simulated ASCII LED light controller on a serial port")
    p.add_argument("--port", required=True, help="serial device, e.g. one end of a socat pty pair")
    p.add_argument("--channels", type=int, default=4)
    p.add_argument("--baudrate", type=int, default=115200)
    p.add_argument("--garbage", action="store_true", help="answer with malformed replies")
    a = p.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    serve(a.port, a.channels, a.baudrate, a.garbage, stop)


if __name__ == "__main__":
    main()
