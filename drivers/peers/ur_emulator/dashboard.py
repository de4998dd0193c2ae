"""The dashboard server (port 29999): the controller's line protocol, one command per line.

Queries (``robotmode``, ``safetystatus``, ``running``, ``PolyscopeVersion``, ...) answer from the
controller's state; actions (``power on``, ``brake release``, ``unlock protective stop``,
``stop``, ...) change it. Replies follow a 5.11 controller's words; unknown commands get its
"could not understand" line.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable

from drivers.peers.ur_emulator.arm import (
    ROBOT_MODE_IDLE,
    ROBOT_MODE_NAMES,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_POWER_ON,
    ROBOT_MODE_RUNNING,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOP,
)
from drivers.peers.ur_emulator.controller import Controller

POLYSCOPE_VERSION = "URSoftware 5.11.1.108318 (Nov 29 2021)"
SERIAL_NUMBER = "20235500001"

_FIXED = {
    "polyscopeversion": POLYSCOPE_VERSION,
    "get serial number": SERIAL_NUMBER,
    "get robot model": "UR5",
    "is in remote control": "true",
    "play": "Failed to execute: play",
    "pause": "Failed to execute: pause",
    "close popup": "closing popup",
    "close safety popup": "closing safety popup",
    "restart safety": "Restarting safety",
    "get loaded program": "No program loaded",
    "isprogramsaved": "true <unnamed>",
}
"""Commands whose answer does not depend on the controller's state."""

_CLOSING = {"quit": "Disconnected", "shutdown": "Shutting down"}
"""Commands after which the server closes the connection."""

_PREFIXED = {
    "popup ": lambda arg: "showing popup",
    "addtolog ": lambda arg: "Added log message",
    "setuserrole ": lambda arg: "Setting user role: " + arg,
    "load ": lambda arg: "File not found: " + arg,
}
"""Commands with an argument: the reply given the argument (as typed)."""


def _safety_name(c: Controller) -> str:
    return "PROTECTIVE_STOP" if c.arm.safety_mode == SAFETY_PROTECTIVE_STOP else "NORMAL"


def _power_on(c: Controller) -> str:
    if c.arm.robot_mode == ROBOT_MODE_POWER_OFF:
        c.arm.robot_mode = ROBOT_MODE_IDLE
    return "Powering on"


def _power_off(c: Controller) -> str:
    c.arm.robot_mode = ROBOT_MODE_POWER_OFF
    c.script.stop(c.arm, "power off")
    return "Powering off"


def _brake_release(c: Controller) -> str:
    if c.arm.robot_mode in (ROBOT_MODE_IDLE, ROBOT_MODE_POWER_ON):
        c.arm.robot_mode = ROBOT_MODE_RUNNING
    return "Brake releasing"


def _unlock_protective_stop(c: Controller) -> str:
    if c.arm.safety_mode != SAFETY_PROTECTIVE_STOP:
        return ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause "
                "of protective stop before unlocking")
    c.arm.safety_mode = SAFETY_NORMAL
    return "Protective stop releasing"


def _stop(c: Controller) -> str:
    c.script.stop(c.arm, "dashboard stop")
    return "Stopped"


_STATEFUL: dict[str, Callable[[Controller], str]] = {
    "robotmode": lambda c: f"Robotmode: {ROBOT_MODE_NAMES.get(c.arm.robot_mode, 'UNKNOWN')}",
    "safetymode": lambda c: f"Safetymode: {_safety_name(c)}",
    "safetystatus": lambda c: f"Safetystatus: {_safety_name(c)}",
    "running": lambda c: f"Program running: {'true' if c.script.program_running else 'false'}",
    "programstate": lambda c: "PLAYING rtde_control" if c.script.program_running else "STOPPED <unnamed>",
    "power on": _power_on,
    "power off": _power_off,
    "brake release": _brake_release,
    "unlock protective stop": _unlock_protective_stop,
    "stop": _stop,
}
"""Commands that read or change the controller (called under its lock)."""


def dashboard_reply(ctrl: Controller, command: str) -> tuple[str, bool]:
    """The dashboard server's answer to one command line, and whether it closes the connection."""
    c = command.lower()
    if c in _FIXED:
        return _FIXED[c], False
    if c in _CLOSING:
        return _CLOSING[c], True
    handler = _STATEFUL.get(c)
    if handler is not None:
        with ctrl.lock:
            return handler(ctrl), False
    for prefix, reply in _PREFIXED.items():
        if c.startswith(prefix):
            return reply(command.split(" ", 1)[1]), False
    return f"could not understand: '{command}'", False


def serve_dashboard(conn: socket.socket, ctrl: Controller, stopping: threading.Event) -> None:
    """Serve one dashboard connection: greet, then answer line by line until quit or close."""
    with contextlib.suppress(OSError):
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buf = b""
        while not stopping.is_set():
            chunk = conn.recv(4096)
            if not chunk:
                break
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                reply, close = dashboard_reply(ctrl, line.decode("utf-8", "replace").strip())
                conn.sendall(reply.encode() + b"\n")
                if close:
                    return
    with contextlib.suppress(OSError):
        conn.close()
