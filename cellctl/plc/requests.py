"""What a PLC may ask of the cell (pick, pick with robot motion, verify), the same for every PLC front end.

Both front ends (Modbus TCP, OPC UA) turn a PLC request into :func:`execute_pick` or
:func:`execute_verify`, which never raise: every failure becomes an :class:`Outcome` with an error
class (what the PLC program should do about it), an error-text index (which text an HMI shows) and
the one-line message. The tables below are the documented ones (docs/plc-modbus.md).

One PLC request runs at a time per process (:data:`PLC_LOCK`): a PLC pick and a PLC verify never
fight over the camera. They run in the calling thread — front ends call them from an executor,
never on their event loop.

A pick with robot motion (``move=True``) is an engineer-level act, refused unless the config says
``plc.allow_motion: true``; it runs ``run_pick(..., move=True)`` and so obeys the robot's motion
owner (another mover: ``TEXT_ROBOT_BUSY``) and its Stop latch (``TEXT_ROBOT_STOPPED``), exactly
as ``POST /pick {"move": true}`` does.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from cellctl.auth import Principal
from cellctl.mapping import NoCalibration
from cellctl.pick.flow import PickError, run_pick
from cellctl.pick.model import ModelFileError
from cellctl.services import Services
from cellctl.store import NotFound, StoreUnavailable
from drivers.base import DriverError, MotionRejected, RobotBusy, RobotStopped

log = logging.getLogger(__name__)

PLC_LOCK = threading.Lock()
VERIFY_TIMEOUT_S = 120.0

# Error classes: what the PLC program should do.
CLASS_NONE = 0
CLASS_REQUEST = 1
"""The request is wrong (command code, recipe number): fix the PLC program or its data."""
CLASS_BUSY = 2
"""A request is running: wait until BUSY clears, then send again."""
CLASS_SETUP = 3
"""The cell is not set up for this (recipe, calibration): call the engineer."""
CLASS_RUNTIME = 4
"""A device or vision failure at run time: retry, then call maintenance."""
CLASS_DRIFT = 5
"""Verify measured a drifted calibration: stop picking, recalibrate."""
CLASS_STOPPED = 6
"""The robot is latched by a Stop: an engineer must resume it (POST /robots/{id}/resume), then send again."""
CLASS_INTERNAL = 9
"""A bug: report it with the service log."""

# Error-text index -> (class, text). The index is what an HMI text list is keyed by.
TEXT_NONE = 0
TEXT_UNKNOWN_COMMAND = 1
TEXT_BUSY = 2
TEXT_UNKNOWN_RECIPE = 3
TEXT_BAD_RECIPE = 4
TEXT_NO_CALIBRATION = 5
TEXT_DEVICE = 6
TEXT_CANNOT_PICK = 7
TEXT_VERIFY_FAILED_TO_RUN = 8
TEXT_DRIFTED = 9
TEXT_TIMEOUT = 10
TEXT_RECIPE_RANGE = 11
TEXT_ROBOT_STOPPED = 12
TEXT_ROBOT_BUSY = 13
TEXT_MOTION_OFF = 14
TEXT_STORE = 15
TEXT_INTERNAL = 99

ERROR_TEXTS: dict[int, tuple[int, str]] = {
    TEXT_NONE: (CLASS_NONE, "no error"),
    TEXT_UNKNOWN_COMMAND: (CLASS_REQUEST, "unknown command code"),
    TEXT_BUSY: (CLASS_BUSY, "refused: a request is running"),
    TEXT_UNKNOWN_RECIPE: (CLASS_SETUP, "unknown recipe number"),
    TEXT_BAD_RECIPE: (CLASS_SETUP, "the recipe cannot be used (invalid part model or settings)"),
    TEXT_NO_CALIBRATION: (CLASS_SETUP, "no active calibration for the recipe's camera and robot"),
    TEXT_DEVICE: (CLASS_RUNTIME, "camera or robot unavailable"),
    TEXT_CANNOT_PICK: (CLASS_SETUP, "the pick cannot be done as the recipe asks"),
    TEXT_VERIFY_FAILED_TO_RUN: (CLASS_RUNTIME, "verify could not run (plate not seen, device error)"),
    TEXT_DRIFTED: (CLASS_DRIFT, "calibration drifted beyond tolerance"),
    TEXT_TIMEOUT: (CLASS_RUNTIME, "the request timed out"),
    TEXT_RECIPE_RANGE: (CLASS_REQUEST, "recipe number out of range (0..65535)"),
    TEXT_ROBOT_STOPPED: (CLASS_STOPPED, "robot stopped: an engineer must resume it"),
    TEXT_ROBOT_BUSY: (CLASS_BUSY, "refused: the robot is moved by another caller (a move, pick or routine)"),
    TEXT_MOTION_OFF: (CLASS_SETUP, "robot motion from the PLC is off (plc.allow_motion in cell.yaml)"),
    TEXT_STORE: (CLASS_RUNTIME, "the store is damaged or unreachable: call the engineer (restore the last backup)"),
    TEXT_INTERNAL: (CLASS_INTERNAL, "internal error (see the service log)"),
}


@dataclass
class Outcome:
    """The answer to one PLC request."""

    ok: bool
    text_index: int = TEXT_NONE
    message: str = ""
    picks: list[dict[str, Any]] = field(default_factory=list)
    """``run_pick``'s picks, best first."""
    verify: dict[str, Any] | None = None
    """``verify``'s result (passed, drift_px, drift_mm...)."""
    picked_index: int | None = None
    """With robot motion: the index in ``picks`` of the pick the robot made (None: the robot did not move)."""
    latency_ms: float = 0.0

    @property
    def error_class(self) -> int:
        return ERROR_TEXTS[self.text_index][0]


def pick_sigma(pick: dict[str, Any]) -> tuple[float | None, float | None]:
    """A pick's 1-sigma uncertainty: position (mm, its largest axis in the base frame) and yaw (deg);
    None when not known (a pick answer's ``uncertainty``)."""
    unc = pick.get("uncertainty") or {}
    sig = [float(s) for s in (unc.get("sigma_mm") or []) if s is not None and math.isfinite(float(s))]
    deg = unc.get("sigma_yaw_deg")
    return (max(sig) if sig else None,
            float(deg) if deg is not None and math.isfinite(float(deg)) else None)


def failure(text_index: int, message: str | None = None) -> Outcome:
    return Outcome(False, text_index, message or ERROR_TEXTS[text_index][1])


def execute_pick(services: Services, recipe_id: int, who: str, move: bool = False) -> Outcome:
    """Run a pick and classify any failure; with ``move`` the robot picks the best reachable part.

    Without ``move`` the robot does not move (the PLC moves it with the answer's poses).
    """
    t0 = time.perf_counter()
    if not 0 <= recipe_id <= 65535:
        out = failure(TEXT_RECIPE_RANGE, f"recipe number {recipe_id} is out of range (0..65535)")
    elif move and not services.config.plc.allow_motion:
        out = failure(TEXT_MOTION_OFF, "a PLC pick with robot motion is off: an engineer sets plc.allow_motion: "
                                       "true in cell.yaml to allow it (or the PLC moves the robot itself)")
    else:
        with PLC_LOCK:
            try:
                answer = run_pick(services, recipe_id, None, move, who)
                picks = list(answer["picks"])
                picked = answer.get("picked")
                index = next((k for k, p in enumerate(picks) if p is picked), None) if move else None
                out = Outcome(True, picks=picks, picked_index=index)
            except RobotStopped as exc:
                out = failure(TEXT_ROBOT_STOPPED, f"robot stopped: an engineer must resume it ({_first_line(exc)})")
            except RobotBusy as exc:
                out = failure(TEXT_ROBOT_BUSY, _first_line(exc))
            except MotionRejected as exc:
                out = failure(TEXT_CANNOT_PICK, f"the robot refused the pick: {_first_line(exc)}")
            except StoreUnavailable as exc:
                out = failure(TEXT_STORE, _first_line(exc))
            except NotFound as exc:
                out = failure(TEXT_UNKNOWN_RECIPE, str(exc))
            except NoCalibration as exc:
                out = failure(TEXT_NO_CALIBRATION, str(exc))
            except (ModelFileError, ValidationError) as exc:
                out = failure(TEXT_BAD_RECIPE, f"recipe {recipe_id} cannot be used: {_first_line(exc)}")
            except PickError as exc:
                out = failure(TEXT_CANNOT_PICK, str(exc))
            except (DriverError, OSError, KeyError) as exc:
                out = failure(TEXT_DEVICE, _first_line(exc))
            except Exception as exc:  # noqa: BLE001 - a PLC request never takes the server down
                log.exception("PLC pick of recipe %d failed", recipe_id)
                out = failure(TEXT_INTERNAL, f"internal error: {_first_line(exc)}")
    out.latency_ms = (time.perf_counter() - t0) * 1e3
    if not out.ok:
        log.warning("PLC pick%s of recipe %d refused/failed: %s", " with motion" if move else "", recipe_id,
                    out.message)
    return out


def robot_motion_status(services: Services) -> dict[str, Any]:
    """The motion status of the cell's robot (``calibration.robot``): latched, owner (cheap: no I/O)."""
    slot = services.cell.robots.get(services.config.calibration.robot)
    if slot is None:
        return {"latched": False, "owner": None}
    status: dict[str, Any] = slot.device.motion.status()
    return status


def execute_verify(services: Services, who: str, timeout_s: float = VERIFY_TIMEOUT_S) -> Outcome:
    """Run the ``verify`` routine as a job (visible in /jobs) and wait for it: started by the service's one
    start (``cellctl.routines.start``: preflight, the robot held still for the job), failures sorted by type."""
    from cellctl.routines.start import StartRefused, start_routine

    t0 = time.perf_counter()
    with PLC_LOCK:
        try:
            job = start_routine(services, "verify", {}, Principal(who, "operator"))
            job = services.jobs.join(job.id, timeout_s)
            if job.state == "running":
                services.jobs.cancel(job.id)
                out = failure(TEXT_TIMEOUT, f"verify did not finish within {timeout_s:.0f} s; cancelled")
            elif job.state == "succeeded" and job.result is not None:
                res = job.result
                if res.get("passed"):
                    out = Outcome(True, verify=res)
                else:
                    out = failure(TEXT_DRIFTED, f"calibration drifted: {_fmt(res.get('drift_px'))} px, "
                                                f"{_fmt(res.get('drift_mm'))} mm (tolerance "
                                                f"{_fmt(res.get('tolerance_px'))} px, "
                                                f"{_fmt(res.get('tolerance_mm'))} mm)")
                    out.verify = res
            else:
                msg = job.error or job.message
                text = TEXT_NO_CALIBRATION if isinstance(job.exception, NoCalibration) else TEXT_VERIFY_FAILED_TO_RUN
                out = failure(text, f"verify: {msg}")
        except StartRefused as exc:
            text = TEXT_NO_CALIBRATION if exc.code == "no_active_calibration" else TEXT_VERIFY_FAILED_TO_RUN
            out = failure(text, f"verify: {exc}")
        except RobotStopped as exc:
            out = failure(TEXT_ROBOT_STOPPED, f"robot stopped: an engineer must resume it ({_first_line(exc)})")
        except RobotBusy as exc:
            out = failure(TEXT_ROBOT_BUSY, _first_line(exc))
        except StoreUnavailable as exc:
            out = failure(TEXT_STORE, _first_line(exc))
        except Exception as exc:  # noqa: BLE001 - a PLC request never takes the server down
            log.exception("PLC verify failed")
            out = failure(TEXT_INTERNAL, f"internal error: {_first_line(exc)}")
    out.latency_ms = (time.perf_counter() - t0) * 1e3
    return out


def _fmt(v: Any) -> str:
    return f"{v:.3f}" if isinstance(v, float) and math.isfinite(v) else "n/a"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
