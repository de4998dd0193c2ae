"""The production runs of one service: at most one per robot, started, paused, resumed, stopped.

The manager checks what a start needs before the run owns the robot: the recipe (a place section
and a gripper device), the robot free (``RobotBusy``) and not latched (``RobotStopped``), and no
run on that robot already (``ProductionRunning``).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from cellctl.errors import CellctlError
from cellctl.pick.recipe import PickError, Recipe
from cellctl.production.frames import FailureFrames
from cellctl.production.gripper import Gripper
from cellctl.production.run import ProductionRun, RunSettings
from cellctl.services import Services
from drivers.base import RobotBase, RobotStopped

log = logging.getLogger(__name__)

class ProductionRunning(CellctlError, RuntimeError):
    """A production run already owns the robot."""


class GripperHolding(CellctlError, RuntimeError):
    """The gripper holds something before a run starts."""


class NoRun(CellctlError, LookupError):
    """No production run has been started in this cell."""


class ProductionManager:
    """Production runs of one service (``services.production``, made on first use)."""

    def __init__(self, services: Services) -> None:
        self.services = services
        self.store = services.store
        self.failure_frames = FailureFrames.for_config(services.config)
        self._runs: dict[str, ProductionRun] = {}
        self._last: ProductionRun | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._stored_last = self._stored_snapshot()
        """The last stored run as a PLC reads it, until a run starts in this service (made once: no store
        access on a server's event loop)."""

    def start(self, recipe_id: int, count: int, who: str, robot_id: str | None = None, camera_id: str | None = None,
              overlap: bool = True) -> ProductionRun:
        stored = self.services.store.get_recipe(recipe_id)
        recipe = Recipe.model_validate(stored.data)
        if recipe.place is None:
            raise PickError(f"recipe {recipe_id} has no place section: production needs one (fixed, grid or located; "
                            "docs/production.md)")
        if recipe.gripper.device is None:
            raise PickError(f"recipe {recipe_id}'s gripper names no device (gripper.device): production must grip "
                            "and check the grip (docs/production.md)")
        d = self.services.config.calibration
        rid = robot_id or recipe.robot_id or d.robot
        cid = camera_id or recipe.camera_id or d.camera
        robot: RobotBase = self.services.cell.robot(rid).ensure_open()
        self.services.cell.camera(cid)  # an unknown camera is refused before the robot is taken
        if Gripper(self.services, recipe.gripper).holding():
            raise GripperHolding(f"gripper {recipe.gripper.device.io_id} holds something: take the part out and "
                                 "open the gripper (POST /production/gripper/open) before a run starts")
        belt = None if recipe.source is None else conveyor_parts(self.services, recipe, rid)
        finishing = self._runs.get(rid)
        if finishing is not None and finishing.status.ended_because is not None:
            finishing.done.wait(10.0)  # it has ended: its last writes and the robot's release follow at once
        with self._lock:
            if self._closed:
                raise ProductionRunning("the service is shutting down: no production run starts now")
            current = self._runs.get(rid)
            if current is not None and not current.ended:
                raise ProductionRunning(f"production run {current.status.run_id} already runs on robot {rid} "
                                        f"({current.status.state}); stop it first (POST /production/stop)")
            session = robot.motion.begin(who, f"production run of recipe {recipe_id}")
            try:
                run_id = self.store.new_run(recipe_id, rid, who)
                settings = RunSettings(recipe_id, stored.version, recipe, rid, cid, count, overlap, who)
                if belt is None:
                    run = ProductionRun(self.services, self.store, settings, robot, session, run_id,
                                        self.failure_frames)
                else:
                    from cellctl.production.conveyor_run import ConveyorRun

                    settings.overlap = False  # the belt run takes its pictures on its own thread
                    run = ConveyorRun(self.services, self.store, settings, robot, session, run_id,
                                      self.failure_frames, **belt)
            except BaseException:
                robot.motion.end(session)
                raise
            self._runs[rid] = run
            self._last = run
        run.start()
        return run

    def run(self, robot_id: str | None = None) -> ProductionRun:
        """The robot's current or last run (default: the last run started)."""
        with self._lock:
            run = self._runs.get(robot_id) if robot_id else self._last
        if run is None:
            raise NoRun("no production run has been started" + (f" on robot {robot_id}" if robot_id else "")
                        + " since the service started (POST /production/start)")
        return run

    def snapshot(self) -> dict[str, Any] | None:
        """The last run started in this service, from memory (None: none yet)."""
        with self._lock:
            run = self._last
        return self._stored_last if run is None else run.snapshot()

    def _stored_snapshot(self) -> dict[str, Any] | None:
        try:
            last = self.store.last_run()
            if last is None:
                return None
            return {"run_id": last["run_id"], "state": last["state"], "ended_because": last["ended_because"],
                    "counters": last.get("counters") or {}, "next_slot": self.store.free_slot(int(last["recipe_id"])),
                    "cycle_median_ms": (last.get("cycle_ms") or {}).get("median"),
                    "last": self.store.last_cycle(int(last["run_id"]))}
        except Exception:  # noqa: BLE001 - the PLC shows no run; REST reads the store itself
            log.exception("production: the last stored run cannot be read")
            return None

    def current(self, robot_id: str | None = None) -> dict[str, Any]:
        """The current or last run as ``GET /production`` shows it (the last stored one after a restart)."""
        try:
            out = self.run(robot_id).public()
        except NoRun:
            last = self.store.last_run()
            if last is None:
                raise
            out = {**last, "next_slot": self.store.free_slot(int(last["recipe_id"]))}
        totals = self.store.totals(exclude_run_id=int(out["run_id"]))
        out["totals"] = {k: totals.get(k, 0) + int(v) for k, v in (out.get("counters") or {}).items()}
        out["slots_in_doubt"] = self.store.slots_in_doubt()
        return out

    def running(self, recipe_id: int | None = None) -> list[ProductionRun]:
        """The runs that have not ended (of ``recipe_id`` when given)."""
        with self._lock:
            runs = list(self._runs.values())
        return [r for r in runs if not r.ended and (recipe_id is None or r.s.recipe_id == recipe_id)]

    def resume(self, robot_id: str | None = None) -> ProductionRun:
        run = self.run(robot_id)
        if run.robot.motion.latched:
            raise RobotStopped(f"robot {run.robot.robot_id} is latched by a Stop; an engineer must resume the robot "
                               f"(POST /robots/{run.robot.robot_id}/resume) first")
        run.resume()
        return run

    def open_gripper(self, recipe_id: int) -> dict[str, Any]:
        """Open the recipe's gripper by hand (refused while a run owns its robot)."""
        recipe = Recipe.model_validate(self.services.store.get_recipe(recipe_id).data)
        busy = self.running()
        if busy:
            raise ProductionRunning(f"production run {busy[0].status.run_id} is running; stop it first")
        gripper = Gripper(self.services, recipe.gripper)
        gripper.open()
        return {"holding": gripper.holding()}

    def shutdown(self, reason: str = "the service is shutting down", timeout_s: float = 10.0) -> list[int]:
        """End every run now (the service stops): each robot halted (not latched), each run ended
        ``stopped`` with ``reason``, its records written; later starts are refused. The runs ended."""
        with self._lock:
            self._closed = True
            runs = [r for r in self._runs.values() if not r.ended]
        for run in runs:
            try:
                run.abort(reason)
            except Exception:  # noqa: BLE001 - every run is still asked to end; the halt's failure is logged
                log.exception("production run %s: halting robot %s at shutdown failed", run.status.run_id,
                              run.robot.robot_id)
        for run in runs:
            run.join(timeout_s)
            if not run.ended:
                log.error("production run %s did not end within %.0f s of the shutdown", run.status.run_id,
                          timeout_s)
        return [r.status.run_id for r in runs]


def conveyor_parts(services: Services, recipe: Recipe, robot_id: str) -> dict[str, Any]:
    """What a belt run needs before it owns the robot: the conveyor (open), its active belt calibration for
    this robot, and the window (the recipe's, else the conveyor's)."""
    from cellctl.production.belt import BeltCalibration

    source = recipe.source
    if source is None:
        raise PickError(f"recipe {recipe.name!r} has no source: it is not a belt recipe")
    conveyor = services.cell.conveyor(source.conveyor_id).ensure_open()
    robot = services.cell.robot(robot_id).ensure_open()
    if not robot.tracks_conveyor():
        raise PickError(f"robot {robot_id} ({type(robot).__name__}) cannot track a conveyor: a belt run needs a robot "
                        "whose controller follows the belt's encoder (docs/conveyor.md)")
    cal = services.store.active("conveyor", source.conveyor_id, robot_id)
    if cal is None:
        raise PickError(f"conveyor {source.conveyor_id} has no active belt calibration for robot {robot_id}: run the "
                        "conveyor-calibrate routine and activate its result (docs/conveyor.md)")
    window = source.window_mm or conveyor.pick_window_mm
    return {"belt": BeltCalibration.from_result(cal.result, cal.id), "conveyor": conveyor,
            "window_mm": (float(window[0]), float(window[1]))}


def manager_for(services: Services) -> ProductionManager:
    """The service's production manager (``services.production``: made on first use)."""
    return services.production


def existing_manager(services: Services) -> ProductionManager | None:
    """The service's production manager if one was made (no store access: safe on an event loop)."""
    return services.production_if_made
