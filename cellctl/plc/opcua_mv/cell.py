"""What the Machine Vision front end asks of the cell: the one module that names the cell's requests
(a pick, a production run's start and stop: requests (:class:`~cellctl.plc.engine.Request`) the OPC UA
server submits to the request engine every front end shares, with its rules: ``plc.allow_motion``,
the Stop latch, one request at a time for the cell) and the robot's Stop, and reads the cell's state.

The functions other than the request builders block (store, devices): the front end calls them from
its executor or a thread, never on its event loop (``cell_problem`` and ``run_snapshot`` read memory).
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from typing import Any

from cellctl.plc.engine import Kind, Request
from cellctl.plc.requests import (
    TEXT_BUSY,
    TEXT_DEVICE,
    TEXT_MOTION_OFF,
    TEXT_RECIPE_RANGE,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
    TEXT_UNKNOWN_RECIPE,
    Outcome,
    robot_motion_status,
)
from cellctl.production.manager import existing_manager
from cellctl.services import Services
from cellctl.store import NotFound

log = logging.getLogger(__name__)

WHO = "plc:opcua-mv"
LATCH_STORE_WAIT_S = 2.0
__all__ = ["TEXT_BUSY", "TEXT_DEVICE", "TEXT_MOTION_OFF", "TEXT_RECIPE_RANGE", "TEXT_ROBOT_BUSY", "TEXT_ROBOT_STOPPED",
           "TEXT_UNKNOWN_RECIPE", "Outcome", "Request", "StoredRecipe", "cell_problem", "configuration_id", "pick",
           "robot_stop", "run_snapshot", "start_run", "stop_run", "stored_recipe", "stored_recipes"]


@dataclass(frozen=True)
class StoredRecipe:
    """A stored recipe as the Machine Vision model names it."""

    recipe_id: int
    name: str
    version: int
    sha256: bytes
    """SHA-256 of the recipe's JSON (keys sorted): a changed recipe has another hash."""


def pick(recipe_id: int) -> Request:
    """One pick of ``recipe_id`` (grab, locate, convert; the robot does not move)."""
    return Request(Kind.PICK, recipe_id)


def start_run(recipe_id: int, count: int) -> Request:
    """Start a production run (only with ``plc.allow_motion: true``)."""
    return Request(Kind.PRODUCTION_START, recipe_id, count)


def stop_run() -> Request:
    """End the production run after its current cycle."""
    return Request(Kind.PRODUCTION_STOP)


def run_snapshot(services: Services) -> dict[str, Any] | None:
    """The last production run from memory (``run_id``, ``state``, ``ended_because``, ``last``...); None: none."""
    manager = existing_manager(services)
    return None if manager is None else manager.snapshot()


def robot_stop(services: Services, reason: str) -> str | None:
    """The robot's Stop (as ``POST /robots/{id}/stop``): latch it, abort what moves it, halt it.

    The latch is set first, so nothing moves the robot again until an engineer resumes it, even when
    the robot cannot be reached. None, or why halting failed (the robot is latched either way)."""
    slot = services.cell.robots.get(services.config.calibration.robot)
    if slot is None:
        return f"no robot {services.config.calibration.robot} in this cell"
    robot = slot.device
    robot.motion.latch(WHO, reason)
    problem = None
    try:
        robot.halt()
    except Exception as exc:  # noqa: BLE001 - the latch holds; the caller reports the halt's failure
        problem = f"latched; halting failed: {exc}"
    if services.latches is not None and not services.latches.wait_stored_blocking(LATCH_STORE_WAIT_S):
        log.error("robot stopped by %s; the latch was not stored within %.0f s", WHO, LATCH_STORE_WAIT_S)
    try:
        services.store.audit(WHO, "robot.stop", robot.robot_id, {"reason": reason}, problem or "ok")
    except Exception as exc:  # noqa: BLE001 - the robot has stopped; the log keeps the record
        log.error("robot stopped by %s (%s); its audit entry was not stored: %s", WHO, reason, exc)
    return problem


def cell_problem(services: Services) -> str | None:
    """Why the cell cannot work now (a device it needs is unreachable, the robot is latched); None: it can."""
    d = services.config.calibration
    robot, camera = services.cell.robots.get(d.robot), services.cell.cameras.get(d.camera)
    for kind, slot, device_id in (("robot", robot, d.robot), ("camera", camera, d.camera)):
        if slot is None or not slot.is_open:
            return f"{kind} {device_id} is unreachable"
    status = robot_motion_status(services)
    if status["latched"]:
        return f"robot {d.robot} is latched by a Stop: an engineer must resume it (POST /robots/{d.robot}/resume)"
    return None


def drift_note(services: Services) -> str | None:
    """The drift alarm as a line for ``SystemState``'s description (from memory: no I/O); None without one."""
    drift = services.drift_if_made
    last = None if drift is None else drift.last()
    if drift is None or not drift.alarm or last is None:
        return None
    return (f"drift alarm: the camera moved ({last['drift_mm']:.3f} mm at the fiducials, rule {last['rule']}); "
            "an engineer re-solves it (POST /drift/resolve) and activates the result")


def stored_recipes(services: Services) -> list[StoredRecipe]:
    """The stored recipes (latest versions), by number."""
    return [_stored(r) for r in services.store.list_recipes()]


def stored_recipe(services: Services, recipe_id: int) -> StoredRecipe | None:
    """Recipe ``recipe_id`` (latest version); None when there is none."""
    try:
        return _stored(services.store.get_recipe(recipe_id))
    except NotFound:
        return None


def configuration_id(services: Services) -> str:
    """The active calibrations as one configuration id: ``camera-<id>/handeye-<id>`` (0: none)."""
    d = services.config.calibration
    cam = services.store.active("camera", d.camera, None)
    he = services.store.active("handeye", d.camera, d.robot)
    return f"camera-{cam.id if cam is not None else 0}/handeye-{he.id if he is not None else 0}"


def _stored(r: Any) -> StoredRecipe:
    digest = hashlib.sha256(json.dumps(r.data, sort_keys=True).encode()).digest()
    return StoredRecipe(int(r.recipe_id), str(r.name), int(r.version), digest)
