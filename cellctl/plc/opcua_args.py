"""Method arguments of the PLC's OPC UA server: checked before any request runs.

asyncua calls a method's Python function with the client's Variants as positional arguments, so a
client that sends one argument too many (or too few) would raise ``TypeError`` inside the server:
``BadUnexpectedError`` and a traceback in the log. :func:`guarded` checks the count first and turns
a client's mistake into a status code: a wrong type or count is ``BadInvalidArgument``, a value
outside its documented range ``BadOutOfRange`` (:class:`BadArgument`); only our own bug is
``BadInternalError`` (logged once with its traceback). Nothing behind a refused call runs, so
hostile arguments never reach the robot.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import ua

from cellctl.errors import CellctlError

log = logging.getLogger(__name__)

Method = Callable[..., Awaitable[Any]]


class BadArgument(CellctlError, ValueError):
    """A client's argument is wrong: ``status`` is the OPC UA status code the call answers."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def invalid(message: str) -> BadArgument:
    return BadArgument(ua.StatusCodes.BadInvalidArgument, message)


def out_of_range(message: str) -> BadArgument:
    return BadArgument(ua.StatusCodes.BadOutOfRange, message)


def status(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def value_of(arg: Any) -> Any:
    """The Python value inside a Variant (None: absent or null, a null structure included)."""
    value = arg.Value if isinstance(arg, ua.Variant) else arg
    if isinstance(value, ua.ExtensionObject) and value.TypeId.is_null() and not value.Body:
        return None
    return value


def int_arg(arg: Any, name: str, low: int, high: int) -> int:
    """An integer argument within ``low..high`` (a Boolean is not an integer)."""
    value = value_of(arg)
    if not isinstance(value, int) or isinstance(value, bool):
        raise invalid(f"{name} must be an integer, got {type(value).__name__}")
    if not low <= value <= high:
        raise out_of_range(f"{name} {value} is out of range ({low}..{high:,})")
    return value


def guarded(name: str, fn: Method, n_args: int, on_refused: Callable[[str], Awaitable[None]] | None = None) -> Method:
    """``fn(parent, *args)`` called only with exactly ``n_args`` arguments; a :class:`BadArgument` it
    raises answers its status code, and any other exception ``BadInternalError`` (never
    ``BadUnexpectedError``). ``on_refused(message)`` is told each refusal (e.g. to show it in ``LastError``)."""

    async def refuse(code: int, message: str) -> ua.StatusCode:
        log.warning("OPC UA %s refused: %s", name, message)
        if on_refused is not None:
            await on_refused(message)
        return status(code)

    async def method(parent: ua.NodeId, *args: Any) -> Any:
        if len(args) != n_args:
            return await refuse(ua.StatusCodes.BadInvalidArgument,
                                f"{name} takes {n_args} argument{'s' if n_args != 1 else ''}, got {len(args)}")
        try:
            return await fn(parent, *args)
        except BadArgument as exc:
            return await refuse(exc.status, f"{name}: {exc}")
        except Exception:  # noqa: BLE001 - our bug: the server answers and goes on
            log.exception("OPC UA method %s failed", name)
            return status(ua.StatusCodes.BadInternalError)

    return method
