"""Calibration targets of the cell (``targets:`` in cell.yaml) and the audit log."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from cellctl.api.deps import Engineer, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError

router = APIRouter(tags=["targets"])


@router.get("/targets")
def list_targets(services: ServicesDep, _: Viewer) -> dict[str, Any]:
    return services.config.targets


@router.get("/targets/{name}")
def get_target(name: str, services: ServicesDep, _: Viewer) -> dict[str, Any]:
    from calibration.targets import target_from_dict

    if name not in services.config.targets:
        raise ApiError(404, "unknown_target", f"no target {name!r}; configured: {sorted(services.config.targets)}")
    desc = services.config.targets[name]
    t = target_from_dict(desc)
    pts = t.points()
    return {"name": name, "description": desc, "summary": t.describe(),
            "points": [{"id": int(i), "x_mm": float(p[0] * 1e3), "y_mm": float(p[1] * 1e3), "z_mm": float(p[2] * 1e3)}
                       for i, p in zip(pts.ids, pts.xyz_m, strict=True)]}


@router.get("/audit")
def audit_log(services: ServicesDep, _: Engineer, limit: int = 100, action: str | None = None
              ) -> list[dict[str, Any]]:
    if not 1 <= limit <= 10000:
        raise ApiError(422, "invalid_request", "limit must be between 1 and 10000")
    return [e.to_dict() for e in services.store.audit_log(limit, action)]
