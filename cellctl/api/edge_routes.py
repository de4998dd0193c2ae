"""What the edge must know of a request's route before anything reads its body: the least role it
needs (read from the route's ``RequireRole`` dependency) and whether it is a safety route.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from fastapi.dependencies.models import Dependant
from fastapi.routing import iter_route_contexts
from starlette.routing import Match
from starlette.types import Scope

from cellctl.api.deps import RequireRole, get_principal
from cellctl.api.pools import SAFETY_ROUTES
from cellctl.config import ROLE_RANK, Role


@dataclass(frozen=True)
class RouteInfo:
    """A route as the edge sees it."""

    template: str
    role: Role | None
    """The least role (None: open to all, and such a route takes no body)."""
    safety: bool
    """Served from the safety pool (``cellctl.api.pools.SAFETY_ROUTES``)."""


class RouteTable:
    """The app's routes with their roles, built once from the app (after every router is included)."""

    def __init__(self, app: Any) -> None:
        self._routes: list[tuple[Any, RouteInfo]] = []
        for rc in iter_route_contexts(app.router.routes):
            template = getattr(rc, "path", None)
            if not isinstance(template, str):
                continue
            dependant = getattr(rc, "dependant", None)
            role = least_role(dependant) if isinstance(dependant, Dependant) else None
            self._routes.append((rc, RouteInfo(template, role, template in SAFETY_ROUTES)))

    def match(self, scope: Scope) -> RouteInfo | None:
        """The route that will serve the request (None: none matches path and method; the app answers 404/405)."""
        for rc, info in self._routes:
            try:
                found, _ = rc.matches(scope)
            except Exception:  # noqa: BLE001 - a route that cannot match this scope is not this request's
                continue
            if found == Match.FULL:
                return info
        return None


def least_role(dependant: Dependant) -> Role | None:
    """The highest role any of the route's ``RequireRole`` dependencies asks ("viewer" for a bare token check)."""
    least: Role | None = None
    for d in _dependencies(dependant):
        role: Role | None = d.call.role if isinstance(d.call, RequireRole) else (
            "viewer" if d.call is get_principal else None)
        if role is not None and (least is None or ROLE_RANK[role] > ROLE_RANK[least]):
            least = role
    return least


def _dependencies(dependant: Dependant) -> Iterator[Dependant]:
    for d in dependant.dependencies:
        yield d
        yield from _dependencies(d)
