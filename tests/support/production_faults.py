"""Faults in a production cycle, and the books kept against the virtual cell's truth (the fault tests
and ``bench/production_faults.py``).

A fault lands at a *phase* of the cycle (``GET /production``'s ``phase``): ``to_pick``, ``closing``,
``lifting``, ``carrying``, ``over_slot``, ``releasing``, ``leaving``, ``between``. After it, an engineer
does what docs/production.md says (:func:`recover`): resume the robot, take a held part out (here:
over a free spot of the pick area, the gripper opened), look at each slot in doubt and confirm it.
:func:`books` then checks the truth against the store: no slot holds two parts, every part is
accounted for (in the pick area, or in a slot the store says is placed or in doubt).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np

from cellctl.production.config import GridPlace

PHASES = ("to_pick", "closing", "lifting", "carrying", "over_slot", "releasing", "leaving", "between")
SLOT_TOL_MM = 5.0
"""A part within this of a slot's centre is in that slot."""


@dataclass
class Books:
    """What the truth and the store say after a fault (and the recovery)."""

    parts_in_slot: dict[int, list[int]] = field(default_factory=dict)
    double: int = 0
    """Parts beyond the first in any slot: must be 0."""
    unaccounted: list[int] = field(default_factory=list)
    """Parts neither in the pick area, nor held after a stopped/interrupted cycle, nor in a slot the store
    knows (a placed record, a slot in doubt, a confirmed one): must be empty."""
    in_doubt: list[int] = field(default_factory=list)


def slot_of(T_base_part: Any, grid: GridPlace) -> int | None:
    p = np.asarray(T_base_part)[:2, 3] * 1e3
    for k in range(grid.slot_count()):
        if float(np.hypot(*(grid.T_slot(k)[:2, 3] * 1e3 - p))) < SLOT_TOL_MM:
            return k
    return None


def records(http: httpx.Client) -> list[dict[str, Any]]:
    """Every cycle record of every run (oldest run first)."""
    last = http.get("/production").json()
    out: list[dict[str, Any]] = []
    for run_id in range(1, int(last["run_id"]) + 1):
        r = http.get(f"/production/runs/{run_id}/cycles")
        if r.status_code == 200:
            out += r.json()
    return out


def books(http: httpx.Client, grid: GridPlace, confirmed: set[int] | None = None) -> Books:
    truth = http.get("/sim/truth").json()
    st = http.get("/production").json()
    recs = records(http)
    known = {int(r["slot"]) for r in recs if r["result"] == "placed" and r.get("slot") is not None}
    doubt = {int(d["slot"]) for d in st.get("slots_in_doubt") or []}
    known |= doubt | (confirmed or set())
    ended_holding = bool(recs) and recs[-1]["result"] in ("stopped", "interrupted")
    b = Books(in_doubt=sorted(doubt))
    for part in truth["parts"]:
        k = slot_of(part["T_base_part"], grid) if part["state"] == "placed" else None
        if k is not None:
            b.parts_in_slot.setdefault(k, []).append(part["id"])
        ok = (part["state"] == "in_area" or (part["state"] == "held" and ended_holding)
              or (k is not None and k in known))
        if not ok:
            b.unaccounted.append(part["id"])
    b.double = sum(len(v) - 1 for v in b.parts_in_slot.values())
    return b


def free_spot_mm(truth: dict[str, Any]) -> tuple[float, float]:
    """The point of the pick area farthest from every part lying there (where a held part is put back)."""
    area = truth["pick_area"]
    lying = [np.asarray(p["T_base_part"])[:2, 3] * 1e3 for p in truth["parts"] if p["state"] == "in_area"]
    best, best_d = (float(np.mean(area["x_mm"])), float(np.mean(area["y_mm"]))), -1.0
    for x in np.linspace(area["x_mm"][0] + 40, area["x_mm"][1] - 40, 9):
        for y in np.linspace(area["y_mm"][0] + 40, area["y_mm"][1] - 40, 7):
            d = min((float(np.hypot(x - q[0], y - q[1])) for q in lying), default=math.inf)
            if d > best_d:
                best, best_d = (float(x), float(y)), d
    return best


def recover(http: httpx.Client, grid: GridPlace, recipe_id: int = 1) -> set[int]:
    """What an engineer does after a fault: resume the robot, put a held part back in the pick area,
    confirm each slot in doubt from what lies there. The slots confirmed occupied."""
    if http.get("/robots/robot0/motion").json().get("latched"):
        assert http.post("/robots/robot0/resume").status_code == 200
    truth = http.get("/sim/truth").json()
    if truth["gripper"]["closed"]:
        if truth["gripper"]["holding"] is not None:
            x, y = free_spot_mm(truth)
            pose = {"x_m": x * 1e-3, "y_m": y * 1e-3, "z_m": 0.03, "rx_rad": math.pi, "ry_rad": 0.0, "rz_rad": 0.0}
            r = http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.5})
            assert r.status_code == 200, r.text
        r = http.post("/production/gripper/open", params={"recipe_id": recipe_id})
        assert r.status_code == 200, r.text
    truth = http.get("/sim/truth").json()
    occupied = {slot_of(p["T_base_part"], grid) for p in truth["parts"] if p["state"] == "placed"}
    confirmed = set()
    for d in http.get("/production").json().get("slots_in_doubt") or []:
        full = d["slot"] in occupied
        r = http.post(f"/production/slots/{d['slot']}/confirm", json={"recipe_id": d["recipe_id"], "occupied": full})
        assert r.status_code == 200, r.text
        if full:
            confirmed.add(int(d["slot"]))
    return confirmed


def wait_phase(http: httpx.Client, phase: str, timeout_s: float = 60.0, poll_s: float = 0.002,
               slow_poll_s: float = 0.03) -> dict[str, Any]:
    """Poll ``GET /production`` until the run is at ``phase``: slowly until the phase before it, then
    every ``poll_s`` (the short phases last tens of milliseconds)."""
    before = PHASES[PHASES.index(phase) - 1] if PHASES.index(phase) > 0 else None
    near = before is None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st: dict[str, Any] = http.get("/production").json()
        if st.get("phase") == phase:
            return st
        if st.get("ended_because") is not None:
            raise AssertionError(f"the run ended before phase {phase}: {st}")
        near = near or st.get("phase") == before
        time.sleep(poll_s if near else slow_poll_s)
    raise TimeoutError(f"phase {phase} not reached in {timeout_s} s")


def wait_run_phase(run: Any, phase: str, timeout_s: float = 60.0) -> None:
    """As :func:`wait_phase` for a run of this process (``ProductionRun.phase``)."""
    before = PHASES[PHASES.index(phase) - 1] if PHASES.index(phase) > 0 else None
    near = before is None
    deadline = time.monotonic() + timeout_s
    while run.phase != phase:
        assert not run.ended, f"the run ended before {phase}"
        assert time.monotonic() < deadline, f"phase {phase} not reached"
        near = near or run.phase == before
        time.sleep(0.0005 if near else 0.02)
