"""Drift monitoring over REST (docs/drift.md): the chart, a check now, the gated re-solve.

- ``GET /drift`` (viewer): ``{"state", "records", "limits": {"center_mm", "ucl_mm", "mr_ucl_mm", ...}}`` (the
  limits null while the baseline is being set);
- ``POST /drift/check`` (operator): one check now on a fresh frame, answering its record;
- ``POST /drift/resolve`` (engineer): the camera's pose re-solved from the fiducials, stored as a new
  hand-eye version, not activated: ``{"calibration_id", "verdict", "shift_mm", "shift_deg"}``; an
  engineer activates it with ``POST /calibrations/{id}/activate`` (audited).

404 ``no_drift`` when cell.yaml has no ``drift:`` section; 409 ``drift_unavailable`` when no check can
be made (no active eye-to-hand hand-eye, or the fiducials are not seen), saying why.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from starlette.concurrency import run_in_threadpool

from cellctl.api.deps import Engineer, Operator, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.drift.monitor import DriftMonitor, DriftUnavailable, limits_json
from cellctl.services import Services

router = APIRouter(prefix="/drift", tags=["drift"])


def _monitor(services: Services) -> DriftMonitor:
    monitor = services.drift
    if monitor is None:
        raise ApiError(404, "no_drift", f"cell {services.config.cell_id!r} has no drift checks: add a drift: section "
                                        "with its fiducials to cell.yaml (docs/drift.md)")
    return monitor


async def _call(services: Services, fn: Any) -> dict[str, Any]:
    try:
        out: dict[str, Any] = await run_in_threadpool(fn)
    except DriftUnavailable as exc:
        raise ApiError(409, "drift_unavailable", str(exc)) from None
    return out


@router.get("")
async def drift(services: ServicesDep, _: Viewer,
                limit: Annotated[int, Query(ge=1, le=10_000, description="the last records shown")] = 200,
                none_ok: Annotated[bool, Query(description="without a drift: section answer 200 with state off "
                                                           "(the page asks so), not 404")] = False,
                ) -> dict[str, Any]:
    """The drift state (``baseline``, ``ok``, ``alarm``, ``no_calibration``; ``off`` with ``none_ok`` and no
    drift checks configured), the last checks (oldest first) and the chart's limits (null while the baseline
    is being set)."""
    if none_ok and services.config.drift is None:
        return {"state": "off", "records": [], "limits": limits_json(None)}
    monitor = _monitor(services)
    return await _call(services, lambda: monitor.public(limit))


@router.post("/check", responses={409: {"description": "drift_unavailable: no check can be made now (why)"}})
async def check(services: ServicesDep, who: Operator) -> dict[str, Any]:
    """One check now on a fresh frame: its record ``{"t", "drift_px", "drift_mm", "drift_deg", "state", "rule",
    ...}`` (``state: failed`` with ``reason`` when the fiducials were not seen)."""
    monitor = _monitor(services)
    return await _call(services, lambda: monitor.check_now(who.name, "request"))


@router.post("/resolve", responses={409: {"description": "drift_unavailable: the fiducials do not give a pose"}})
async def resolve(services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Re-solve the camera's pose from the fiducials (intrinsics and robot side kept) into a new hand-eye
    version, not activated: ``{"calibration_id", "verdict", "shift_mm", "shift_deg"}``."""
    monitor = _monitor(services)
    return await _call(services, lambda: monitor.resolve(who.name))
