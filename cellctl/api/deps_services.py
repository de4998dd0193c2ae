"""The ``Services`` dependency (kept apart from deps.py so routers import only what they use)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from cellctl.services import Services


async def get_services(request: Request) -> Services:
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]
