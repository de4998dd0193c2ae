"""Runs the service did not end: ended ``interrupted`` at the next start, before anything is served.

A service killed (kill -9, a crash, the power) while a run went leaves the run stored as running,
its last cycle unrecorded and maybe a slot claimed for a part on its way. At the next start:

- every claim still ``claimed`` becomes ``in_doubt`` (``Store.claims_in_doubt_at_start``): no run
  places there until an engineer confirms the slot (``POST /production/slots/{slot}/confirm``);
- each such run gets a last cycle record ``interrupted`` with where it was (the last stored phase:
  ``to_pick``, ``carrying`` with the part held, ``leaving`` with it let go ...), the slot in doubt
  and the part it held, and ends ``interrupted`` / ``interrupted``;
- the robot of a run that was moving it (stored ``running``, ``pausing`` or ``stopping``; a
  ``paused`` run stood still) is latched as after a Stop, stored with its audit entry: an engineer
  checks the cell and resumes the robot (``POST /robots/{id}/resume``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

from cellctl.store import Store
from drivers.motion import MotionOwner

log = logging.getLogger(__name__)

LATCHED_BY = "cellctl"
MOVING_STATES = ("running", "pausing", "stopping")
HELD_BY_PHASE: dict[str, bool | None] = {"to_pick": None, "carrying": True, "leaving": False}
"""Whether the gripper held the part at the last stored phase (None: not known: it may have closed)."""


def end_interrupted_runs(store: Store, owners: Mapping[str, MotionOwner]) -> list[dict[str, Any]]:
    """End every run the store holds as not ended (see the module docstring); the runs ended."""
    now = time.time()
    in_doubt = store.claims_in_doubt_at_start(
        f"the service ended before the run knew the part was placed (found at the start at {_utc(now)})")
    ended = []
    for run in store.unended_runs():
        run_id, robot_id = int(run["run_id"]), str(run["robot_id"])
        progress = run.get("progress") or {}
        phase = str(progress.get("phase") or "unknown")
        doubt = [c for c in in_doubt if c["run_id"] == run_id]
        slot = doubt[0]["slot"] if doubt else None
        moving = run["state"] in MOVING_STATES
        why = (f"the service ended while the run was {run['state']} (phase {phase}) and did not end it; "
               f"ended interrupted at the start at {_utc(now)}")
        last = store.last_cycle(run_id)
        n = (int(last["n"]) if last is not None else 0) + 1
        record = {"n": n, "t": now, "run_id": run_id, "result": "interrupted", "slot": slot,
                  "slot_state": "in_doubt" if slot is not None else None, "phase": phase,
                  "held": HELD_BY_PHASE.get(phase), "pick_pose": progress.get("pick_pose"),
                  "recipe_id": run["recipe_id"], "detail": why + (
                      f"; slot {slot} is in doubt until an engineer confirms it" if slot is not None else "")}
        store.add_cycle(run_id, record)
        summary: dict[str, Any] = {k: run.get(k) for k in ("counters", "cycle_ms", "error", "stop_reason", "cycles")
                                   if k in run}
        summary.update({"stop_reason": why, "cycles": n, "interrupted": {"phase": phase, "state": run["state"],
                                                                         "slot_in_doubt": slot}})
        store.update_run(run_id, "interrupted", "interrupted", summary, ended=True)
        log.warning("production run %s: %s", run_id, why)
        if moving:
            _latch(store, owners, robot_id, f"production run {run_id} was moving the robot when the service ended "
                                            f"(phase {phase}); check the cell, then resume the robot", now)
        ended.append({"run_id": run_id, "robot_id": robot_id, "phase": phase, "slot_in_doubt": slot,
                      "latched": moving})
    return ended


def _latch(store: Store, owners: Mapping[str, MotionOwner], robot_id: str, reason: str, now: float) -> None:
    owner = owners.get(robot_id)
    if owner is not None:
        owner.latch(LATCHED_BY, reason, since_s=now)
    try:
        store.set_latch(robot_id, LATCHED_BY, reason, now, result=f"latched at start: {reason}")
    except Exception as exc:  # noqa: BLE001 - latched in memory; only its record is missing
        log.error("robot %s: storing its latch at start failed: %s", robot_id, exc)


def _utc(at_s: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(at_s))
