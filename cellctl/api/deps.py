"""Shared route dependencies: the live cell, the caller's identity and role checks, device calls."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from cellctl.api.errors import ApiError
from cellctl.api.pools import run_blocking
from cellctl.auth import Principal, TokenTable
from cellctl.cell import Cell, DeviceSlot
from cellctl.config import Role
from drivers.base import DeviceTimeout, DeviceUnavailable, DriverError

T = TypeVar("T")

DEVICE_CALL_TIMEOUT_S = 3.0
_bearer = HTTPBearer(auto_error=False)


async def get_cell(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


CellDep = Annotated[Cell, Depends(get_cell)]

# The dependencies below are async on purpose: they do no blocking work, and an async dependency
# runs on the event loop, so a request needs no worker thread to pass them (cellctl.api.pools).

MISSING_TOKEN = "missing bearer token: send 'Authorization: Bearer <token>'"
UNKNOWN_TOKEN = "unknown token: ask the cell's engineer for a valid token"
PRINCIPAL_KEY = "cellctl.principal"
"""Where the edge (cellctl.api.middleware) leaves the caller it has authenticated, in the ASGI scope."""


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header (any spacing, scheme in any case), else None."""
    parts = (authorization or "").split()
    return parts[1] if len(parts) == 2 and parts[0].lower() == "bearer" else None


def authenticate(tokens: TokenTable, authorization: str | None) -> Principal | ApiError:
    """The caller of an ``Authorization`` header, or the 401 to answer."""
    token = bearer_token(authorization)
    if token is None:
        return ApiError(401, "unauthorized", MISSING_TOKEN)
    principal = tokens.lookup(token)
    return principal if principal is not None else ApiError(401, "unauthorized", UNKNOWN_TOKEN)


def role_refusal(principal: Principal, role: Role) -> ApiError | None:
    """The 403 when ``principal`` has less than ``role``, else None."""
    if principal.has(role):
        return None
    return ApiError(403, "forbidden", f"this needs the {role} role; token {principal.name!r} has {principal.role}")


async def get_principal(request: Request,
                        creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> Principal:
    found = request.scope.get(PRINCIPAL_KEY)
    if not isinstance(found, Principal):
        found = authenticate(request.app.state.tokens, request.headers.get("authorization"))
    if isinstance(found, ApiError):
        raise found
    request.state.principal = found
    return found


class RequireRole:
    """A dependency that lets callers with at least ``role`` through (403 otherwise).

    The edge reads ``role`` from each route's dependencies to refuse a caller before its body is read.
    """

    def __init__(self, role: Role) -> None:
        self.role: Role = role

    async def __call__(self, principal: Annotated[Principal, Depends(get_principal)]) -> Principal:
        refusal = role_refusal(principal, self.role)
        if refusal is not None:
            raise refusal
        return principal


def require(role: Role) -> RequireRole:
    return RequireRole(role)


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

    The call runs in the request's pool (``cellctl.api.pools``: a Stop's in the safety pool).

    A call that times out or finds the device gone marks the slot unavailable, so the next call
    answers at once and the slot reconnects by itself after its back-off.
    """
    try:
        await run_blocking(slot.ensure_open)
        return await asyncio.wait_for(run_blocking(fn, slot.device), timeout_s)
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
