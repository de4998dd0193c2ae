"""Production from a PLC: start, pause, resume and stop a run, and the run's state as registers.

Shared by the PLC front ends like ``cellctl.plc.requests``: :func:`execute_production` never raises
(every failure is an :class:`~cellctl.plc.requests.Outcome` with the documented error class and
text); :func:`production_words` is the run's state as the Modbus production block and :func:`doubt_words`
the slots in doubt as the in-doubt block (docs/plc-modbus.md).
Starting (and resuming) a run moves the robot: only with ``plc.allow_motion: true``.
"""

from __future__ import annotations

import logging
from typing import Any

from pydantic import ValidationError

from cellctl.cell import UnknownDevice
from cellctl.mapping import NoCalibration
from cellctl.pick.recipe import PickError
from cellctl.plc.requests import (
    TEXT_BAD_RECIPE,
    TEXT_CANNOT_PICK,
    TEXT_DEVICE,
    TEXT_INTERNAL,
    TEXT_MOTION_OFF,
    TEXT_NO_CALIBRATION,
    TEXT_RECIPE_RANGE,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
    TEXT_UNKNOWN_RECIPE,
    Outcome,
    failure,
)
from cellctl.production.manager import GripperHolding, NoRun, ProductionRunning, existing_manager, manager_for
from cellctl.services import Services
from cellctl.store import NotFound
from drivers.base import DriverError, RobotBusy, RobotStopped

log = logging.getLogger(__name__)

CMD_PRODUCTION_START, CMD_PRODUCTION_PAUSE, CMD_PRODUCTION_RESUME, CMD_PRODUCTION_STOP = 4, 5, 6, 7
PRODUCTION_COMMANDS = (CMD_PRODUCTION_START, CMD_PRODUCTION_PAUSE, CMD_PRODUCTION_RESUME, CMD_PRODUCTION_STOP)

STATES = {"running": 1, "pausing": 2, "paused": 3, "stopping": 4, "stopped": 5, "complete": 6, "failed": 7,
          "interrupted": 8}
ENDED = {"count_reached": 1, "area_empty": 2, "none_pickable": 3, "stopped": 4, "failed": 5, "interrupted": 6,
         "not_recognized": 7}
RESULTS = {"placed": 1, "grip_failed": 2, "skipped": 3, "empty": 4, "none_pickable": 5, "stopped": 6,
           "vision_failed": 7, "interrupted": 8, "not_recognized": 9, "missed_window": 10, "belt_stopped": 11}
COUNTERS = ("picked", "placed", "grip_failures", "retries", "skipped", "empty_area", "unreachable")


def execute_production(services: Services, command: int, recipe_id: int, count: int, who: str) -> Outcome:
    """Start (recipe, count), pause, resume or stop the production run; classify any failure."""
    manager = manager_for(services)
    try:
        if command == CMD_PRODUCTION_START:
            if not 0 <= recipe_id <= 65535:
                return failure(TEXT_RECIPE_RANGE, f"recipe number {recipe_id} is out of range (0..65535)")
            if not services.config.plc.allow_motion:
                return failure(TEXT_MOTION_OFF, "a production run moves the robot: an engineer sets "
                                                 "plc.allow_motion: true in cell.yaml to let the PLC start one")
            manager.start(recipe_id, count, who)
        elif command == CMD_PRODUCTION_PAUSE:
            manager.run().pause()
        elif command == CMD_PRODUCTION_RESUME:
            if not services.config.plc.allow_motion:
                return failure(TEXT_MOTION_OFF, "resuming a production run moves the robot: only with "
                                                 "plc.allow_motion: true")
            manager.resume()
        else:
            manager.run().stop()
        services.store.audit(who, f"production.plc.{command}", str(recipe_id), {"count": count}, "ok")
        return Outcome(True)
    except RobotStopped as exc:
        return failure(TEXT_ROBOT_STOPPED, f"robot stopped: an engineer must resume it ({_line(exc)})")
    except (RobotBusy, ProductionRunning, GripperHolding) as exc:
        return failure(TEXT_ROBOT_BUSY, _line(exc))
    except NotFound as exc:
        return failure(TEXT_UNKNOWN_RECIPE, str(exc))
    except NoRun as exc:
        return failure(TEXT_CANNOT_PICK, str(exc))
    except NoCalibration as exc:
        return failure(TEXT_NO_CALIBRATION, str(exc))
    except ValidationError as exc:
        return failure(TEXT_BAD_RECIPE, f"recipe {recipe_id} cannot be used: {_line(exc)}")
    except PickError as exc:
        return failure(TEXT_CANNOT_PICK, str(exc))
    except (DriverError, OSError, UnknownDevice) as exc:
        return failure(TEXT_DEVICE, _line(exc))
    except Exception as exc:  # noqa: BLE001 - a PLC request never takes the server down
        log.exception("PLC production command %d failed", command)
        return failure(TEXT_INTERNAL, f"internal error: {_line(exc)}")


def production_values(services: Services) -> dict[str, Any]:
    """The last run's state as numbers (0 where there is none), from memory."""
    manager = existing_manager(services)
    snap = None if manager is None else manager.snapshot()
    if snap is None:
        return {"run_id": 0, "state": 0, "ended": 0, "counters": [0] * len(COUNTERS), "next_slot": -1,
                "last_result": 0, "last_slot": -1, "cycle_median_ms": -1, "sigma_mm": -1, "sigma_deg": -1}
    last = snap["last"] or {}
    unc = last.get("uncertainty") or {}
    sig = [s for s in (unc.get("sigma_mm") or []) if s is not None]
    sigma_deg = unc.get("sigma_yaw_deg")
    median = snap["cycle_median_ms"]
    return {"run_id": snap["run_id"], "state": STATES.get(snap["state"], 0),
            "ended": ENDED.get(snap["ended_because"] or "", 0),
            "counters": [int(snap["counters"].get(k, 0)) for k in COUNTERS], "next_slot": int(snap["next_slot"]),
            "last_result": RESULTS.get(str(last.get("result")), 0),
            "last_slot": -1 if last.get("slot") is None else int(last["slot"]),
            "cycle_median_ms": -1 if median is None else median,
            "sigma_mm": max(sig) if sig else -1, "sigma_deg": -1 if sigma_deg is None else sigma_deg}


def conveyor_words(services: Services) -> list[int]:
    """The Modbus conveyor block: the last run's ``missed_window`` and the parts queued on its belt now."""
    from cellctl.plc.modbus_map import conveyor_block_words

    manager = existing_manager(services)
    snap = None if manager is None else manager.snapshot()
    if snap is None:
        return conveyor_block_words(0, 0)
    return conveyor_block_words(int((snap["counters"] or {}).get("missed_window", 0)), int(snap.get("queue_length", 0)))


def production_words(services: Services) -> list[int]:
    """The Modbus production block (docs/plc-modbus.md) from :func:`production_values`, laid out by the
    register map's table (``cellctl.plc.modbus_map.PRODUCTION_FIELDS``)."""
    from cellctl.plc.modbus_map import production_block_words

    return production_block_words(production_values(services))


def doubt_values(services: Services) -> tuple[int | None, int | None, int | None]:
    """(count, first recipe, first slot) of the cell's slots in doubt; count None when the store cannot
    say (the store keeps the summary in memory: ``Store.doubt_summary``)."""
    try:
        d = services.store.doubt_summary()
    except Exception as exc:  # noqa: BLE001 - the PLC is told "not known", never a stale zero
        log.warning("the slots in doubt cannot be read from the store: %s", _line(exc))
        return None, None, None
    return d.count, d.recipe_id, d.slot


def doubt_words(services: Services) -> list[int]:
    """The Modbus in-doubt block (docs/plc-modbus.md: DOUBT_COUNT, DOUBT_RECIPE, DOUBT_SLOT)."""
    from cellctl.plc.modbus_map import doubt_block_words

    return doubt_block_words(*doubt_values(services))


def _line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
