"""``GET /auth/whoami``: the caller's token name and role (the operator page uses it to log in)."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel

from cellctl.api.deps import Viewer

router = APIRouter(prefix="/auth", tags=["auth"])


class WhoAmI(BaseModel):
    name: str
    role: str


@router.get("/whoami", response_model=WhoAmI)
def whoami(who: Viewer) -> dict[str, str]:
    return {"name": who.name, "role": who.role}
