"""The robot socket: one ASCII line in, one line out, for a robot program's own TCP client.

With ``plc.robot_socket.enabled`` (default 127.0.0.1:5021) a robot program (ABB RAPID
``SocketSend``, FANUC User Socket Msg, KUKA EKI, Yaskawa MotoPlus) sends one line ended by ``\\n``
or ``\\r\\n`` and reads one back (docs/robot-socket.md):

- ``PICK <recipe>`` -> ``OK <n> <x_mm> <y_mm> <z_mm> <a> <b> <c> <score> <sigma_mm>``: the best
  *reachable* pick of the recipe, ``n`` the picks found; the orientation ``<a> <b> <c>`` in the
  convention ``plc.robot_socket.pose_format`` (``ur`` rotation vector in rad; ``abb`` quaternion
  q1..q4, four numbers; ``fanuc`` W P R, ``yaskawa`` Rx Ry Rz, degrees about the fixed X, Y, Z;
  ``kuka`` A B C, degrees about Z, Y', X''); ``sigma_mm`` -1 when not known. Nothing reachable:
  ``ERR 7 ...``.
- ``VERIFY`` -> ``OK <drift_px> <drift_mm>`` (``drift_mm`` -1 without a hand-eye calibration).
- ``STATUS`` -> ``OK <latched 0|1> <busy 0|1> <run_state>`` (run_state: the Modbus RUN_STATE code,
  0 no run, 1 running ... 8 interrupted).
- anything else -> ``ERR 1 ...``; every failure is ``ERR <code> <text>`` with ``code`` the PLC
  error-text index (docs/plc-modbus.md), e.g. ``ERR 2`` busy, ``ERR 3`` unknown recipe.

A line over 256 bytes is answered ``ERR 1`` and the connection closed; a client silent for
``idle_timeout_s`` (60) is closed; more than ``max_clients`` (4) at once are answered ``ERR 2``
and closed. Requests go through the request engine (one at a time for the cell); the socket never
moves the robot (the robot program does, with the pose it read).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
from collections.abc import Callable
from typing import Any

from calibration import geometry as g
from cellctl.config_listeners import RobotSocketConfig
from cellctl.plc.engine import Engine, Kind, Request
from cellctl.plc.production import production_values
from cellctl.plc.quiet_log import client_mistake
from cellctl.plc.requests import (
    TEXT_BUSY,
    TEXT_CANNOT_PICK,
    TEXT_RECIPE_RANGE,
    TEXT_UNKNOWN_COMMAND,
    Outcome,
    pick_sigma,
    robot_motion_status,
)
from cellctl.plc.stream_server import StreamServer
from cellctl.services import Services
from drivers.loop_thread import LoopNotRunning

log = logging.getLogger(__name__)

MAX_LINE = 256
"""Bytes in one request line, its end included."""
HELP = "use PICK <recipe>, VERIFY or STATUS"


def _line(text: str) -> bytes:
    return (text + "\r\n").encode("ascii", "replace")


def err(code: int, text: str) -> str:
    """``ERR <code> <text>``, the text on one line."""
    return f"ERR {code} " + " ".join(text.split())


def format_pick(out: Outcome, pose_format: str) -> str:
    """The ``PICK`` answer: the best reachable pick in the robot's convention, or ``ERR``."""
    if not out.ok:
        return err(out.text_index, out.message)
    best = next((p for p in out.picks if p.get("reachable")), None)
    if best is None:
        return err(TEXT_CANNOT_PICK, f"no reachable pick ({len(out.picks)} found)")
    pose = best["pick_pose"]
    R = g.rotvec_to_matrix([pose["rx_rad"], pose["ry_rad"], pose["rz_rad"]])
    angles = g.matrix_to_robot_orientation(R, pose_format)
    digits = 6 if pose_format in ("ur", "abb") else 4
    sigma_mm, _ = pick_sigma(best)
    fields = [str(len(out.picks)), *(f"{float(pose[k]):.3f}" for k in ("x_mm", "y_mm", "z_mm")),
              *(f"{a:.{digits}f}" for a in angles), f"{float(best['score']):.3f}",
              "-1" if sigma_mm is None else f"{sigma_mm:.4f}"]
    return "OK " + " ".join(fields)


def format_verify(out: Outcome) -> str:
    v = out.verify
    if v is None:
        return err(out.text_index, out.message)
    if not out.ok:
        return err(out.text_index, out.message)
    px, mm = v.get("drift_px"), v.get("drift_mm")
    return "OK " + " ".join("-1" if x is None or not math.isfinite(float(x)) else f"{float(x):.4f}" for x in (px, mm))


class RobotSocketServer(StreamServer):
    """The robot socket for one cell; ``start()`` listens, ``stop()`` ends it (``StreamServer``)."""

    name, setting, title = "robot_socket", "plc.robot_socket", "PLC robot socket"
    motion = False  # the socket never moves the robot: no zone key needed for its address
    line_limit = MAX_LINE + 2
    config: RobotSocketConfig

    def __init__(self, services: Services, config: RobotSocketConfig, engine: Engine | None = None) -> None:
        super().__init__(services, config, engine)

    def start(self) -> RobotSocketServer:
        super().start()
        log.info("PLC robot socket on %s:%d (pose format %s)", self.config.host, self.address[1],
                 self.config.pose_format)
        return self

    async def refuse(self, writer: asyncio.StreamWriter) -> None:
        await self.send_and_close(writer, _line(err(TEXT_BUSY, f"too many clients (at most "
                                                               f"{self.config.max_clients}); try again later")))

    async def serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                           addr: tuple[str, int]) -> None:
        too_long = _line(err(TEXT_UNKNOWN_COMMAND, f"line longer than {MAX_LINE} bytes; {HELP}"))
        while True:
            try:
                raw = await self.within_idle(reader.readuntil(b"\n"), addr)
            except asyncio.LimitOverrunError:
                client_mistake(log, "over-long robot socket lines", "PLC robot socket: closed the client %s: a "
                               "line longer than %d bytes", addr[0], MAX_LINE)
                await self.send_and_close(writer, too_long)
                return
            except asyncio.IncompleteReadError as exc:
                if len(exc.partial) > MAX_LINE:
                    await self.send_and_close(writer, _line(err(TEXT_UNKNOWN_COMMAND, "line too long")))
                return
            if raw is None:
                return
            if len(raw) > MAX_LINE:
                await self.send_and_close(writer, too_long)
                return
            writer.write(_line(await self._answer(raw)))
            await writer.drain()

    async def _answer(self, raw: bytes) -> str:
        """One request line's answer (never raises for a client's line). The line's parsing is paced
        (``self.pacer``); the wait for the engine's answer is not (it is not this front end's work)."""
        t0 = await self.pacer.wait()
        try:
            parsed = self._parse(raw)
        finally:
            self.pacer.done(t0)
        if isinstance(parsed, str):
            return parsed
        request, answer = parsed
        if self._front is None:
            raise LoopNotRunning("the robot socket server is not started: start() registers its front end")
        return answer(await asyncio.wrap_future(self.engine.submit(self._front, request, "plc:robot_socket")))

    def _parse(self, raw: bytes) -> str | tuple[Request, Callable[[Outcome], str]]:
        """The answer to a line, or the request it asks for and how to word its outcome."""
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            client_mistake(log, "binary robot socket lines", "PLC robot socket: a line that is not ASCII")
            return err(TEXT_UNKNOWN_COMMAND, f"not an ASCII line; {HELP}")
        if not line.isprintable():
            return err(TEXT_UNKNOWN_COMMAND, f"control characters in the line; {HELP}")
        words = line.split()
        verb = words[0].upper() if words else ""
        if verb == "STATUS" and len(words) == 1:
            return self._status()
        if verb == "VERIFY" and len(words) == 1:
            return Request(Kind.VERIFY), format_verify
        if verb == "PICK":
            if len(words) != 2 or not words[1].isdigit():
                return err(TEXT_RECIPE_RANGE if len(words) == 2 else TEXT_UNKNOWN_COMMAND,
                           "PICK needs one recipe number 0..65535, e.g. PICK 1")
            recipe = int(words[1]) if len(words[1]) <= 6 else 10**6
            return Request(Kind.PICK, recipe), functools.partial(format_pick, pose_format=self.config.pose_format)
        shown = line[:40] + ("..." if len(line) > 40 else "")
        return err(TEXT_UNKNOWN_COMMAND, f"unknown request {shown!r}; {HELP}")

    def _status(self) -> str:
        motion: dict[str, Any] = robot_motion_status(self.services)
        state = production_values(self.services)["state"]
        return f"OK {1 if motion['latched'] else 0} {1 if self.engine.busy else 0} {int(state)}"
