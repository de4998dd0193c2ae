"""Shared route dependencies: the live cell, the caller's identity and role checks, device calls."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from cellctl.api.errors import ApiError
from cellctl.auth import Principal, TokenTable
from cellctl.cell import Cell, DeviceSlot
from cellctl.config import Role
from drivers.base import DeviceTimeout, DeviceUnavailable, DriverError

T = TypeVar("T")

DEVICE_CALL_TIMEOUT_S = 3.0
_bearer = HTTPBearer(auto_error=False)


def get_cell(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


CellDep = Annotated[Cell, Depends(get_cell)]


def get_principal(request: Request,
                  creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> Principal:
    if creds is None or creds.scheme.lower() != "bearer":
        raise ApiError(401, "unauthorized", "missing bearer token: send 'Authorization: Bearer <token>'")
    tokens: TokenTable = request.app.state.tokens
    principal = tokens.lookup(creds.credentials)
    if principal is None:
        raise ApiError(401, "unauthorized", "unknown token: ask the cell's engineer for a valid token")
    request.state.principal = principal
    return principal


def require(role: Role) -> Callable[..., Principal]:
    """A dependency that lets callers with at least ``role`` through (403 otherwise)."""

    def check(principal: Annotated[Principal, Depends(get_principal)]) -> Principal:
        if not principal.has(role):
            raise ApiError(403, "forbidden", f"this needs the {role} role; token {principal.name!r} "
                                             f"has {principal.role}")
        return principal

    return check


Viewer = Annotated[Principal, Depends(require("viewer"))]
Operator = Annotated[Principal, Depends(require("operator"))]
Engineer = Annotated[Principal, Depends(require("engineer"))]


def slot_or_404(slots: dict[str, DeviceSlot[Any]], kind: str, device_id: str) -> DeviceSlot[Any]:
    """The configured device's slot, or a 404 naming the configured ones (``kind``: camera, robot)."""
    if device_id not in slots:
        raise ApiError(404, f"unknown_{kind}", f"no {kind} {device_id!r}; configured: {sorted(slots)}")
    return slots[device_id]


async def device_call(slot: DeviceSlot, fn: Callable[..., T], timeout_s: float = DEVICE_CALL_TIMEOUT_S) -> T:
    """Run a blocking device call off the event loop with a deadline; outages become 503s.

    A call that times out or finds the device gone marks the slot unavailable, so the next call
    answers at once and the slot reconnects by itself after its back-off.
    """
    try:
        await run_in_threadpool(slot.ensure_open)
        return await asyncio.wait_for(run_in_threadpool(fn, slot.device), timeout_s)
    except TimeoutError as exc:
        err = DeviceTimeout(f"{slot.category} {slot.device_id} did not answer within {timeout_s:.1f} s")
        slot.report_failure(err)
        raise err from exc
    except DeviceUnavailable as exc:
        if slot.is_open:
            slot.report_failure(exc)
        raise
    except (DriverError, OSError) as exc:
        if isinstance(exc, ConnectionError | DeviceTimeout):
            slot.report_failure(exc)
        raise
