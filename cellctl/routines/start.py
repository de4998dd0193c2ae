"""Starting a routine: the one place that holds the start rules, for REST and every PLC front end.

``start_routine`` checks, in order: the routine exists, the parameters are a JSON object that its
``Params`` accepts (strict JSON numbers), the caller's role (a routine that moves the robot needs
the engineer role), ``preflight`` (what the config and the store already decide), then takes the
robot's motion for the routine's whole run (a routine that moves it, or measures with it standing
still: ``RobotBusy`` while another caller moves it) and starts the job; the start is audited.
Every refusal is typed: ``StartRefused`` (with an HTTP-like ``status`` and a ``code``),
``drivers.base.RobotBusy`` / ``RobotStopped`` from the motion owner.
"""

from __future__ import annotations

import json
from typing import Any

from pydantic import ValidationError

from cellctl.auth import Principal
from cellctl.errors import CellctlError
from cellctl.errors_format import format_validation_errors
from cellctl.jobs import Job, TooManyJobs
from cellctl.routines import ENGINEER_ONLY, HOLDS_ROBOT, MOVES_ROBOT, ROUTINE_MODULES, routine
from cellctl.routines.preflight import PreflightRefused, preflight
from cellctl.services import Services


class StartRefused(CellctlError):
    """A routine was not started: ``status`` (404 unknown, 403 role, 422 parameters, 409 the cell's state,
    429 too many jobs), ``code`` (machine-readable) and the message (what to change)."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code


def start_routine(services: Services, name: str, params: Any, who: Principal) -> Job:
    """Start routine ``name`` with ``params`` (a JSON object, or None for the defaults) for ``who``."""
    if name not in ROUTINE_MODULES:
        raise StartRefused(404, "unknown_routine",
                           f"no routine {name!r}; routines: {', '.join(sorted(ROUTINE_MODULES))}")
    if params is not None and not isinstance(params, dict):
        raise StartRefused(422, "invalid_params", f"routine {name}: the body must be a JSON object of parameters "
                                                  "(GET /routines lists them)")
    given: dict[str, Any] = params or {}
    # Routines that move the robot need the engineer role (an operator may present the plate by hand).
    moves = name in MOVES_ROBOT and given.get("mode", "robot") == "robot"
    # jog-to-mark's tool-centre step moves the robot too, under a motion session of its own (the
    # operator jogs freely before it), so it needs the role but not the motion from the start.
    turns = name == "jog-to-mark" and given.get("tool_centre") is True
    if not who.has("engineer") and (moves or turns or name in ENGINEER_ONLY):
        raise StartRefused(403, "forbidden",
                           f"routine {name} needs the engineer role; token {who.name!r} has {who.role}")
    module = routine(name)
    try:
        # Strict in JSON terms: a number is a JSON number (not true or "0.4"); JSON integers are fine floats.
        checked = module.Params.model_validate_json(json.dumps(given), strict=True)
    except ValidationError as exc:
        msg = format_validation_errors(exc, with_input=False, model=module.Params)
        raise StartRefused(422, "invalid_params", f"routine {name}: {msg} (GET /routines lists the parameters)"
                           ) from None
    try:
        # What the config and the store decide is answered now, not by a job that fails a moment later.
        preflight(services, name, checked)
    except PreflightRefused as exc:
        raise StartRefused(exc.status, exc.code, f"routine {name}: {exc}") from None
    motion = None
    robot_id = given.get("robot_id") or services.config.calibration.robot
    # A routine that measures with the robot still owns it too (when the cell has it), without moving it.
    holds = name in HOLDS_ROBOT and (given.get("robot_id") is not None or robot_id in services.cell.robots)
    if moves or holds:
        # The routine owns the robot's motion from now to its end: a second mover gets RobotBusy.
        robot = services.cell.robot(str(robot_id)).device
        motion = (robot, robot.motion.begin(who.name, f"routine {name}", still=holds and not moves))
    try:
        job = services.jobs.start(name, lambda ctx: module.run(services, ctx), given, who.name, motion)
    except TooManyJobs as exc:
        if motion is not None:
            motion[0].motion.end(motion[1])
        raise StartRefused(429, "too_many_jobs", str(exc)) from None
    services.store.audit(who.name, "routine.start", name, {"job_id": job.id, "params": given}, "started")
    return job
