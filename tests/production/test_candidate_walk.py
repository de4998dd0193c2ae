"""A candidate's walk through one production cycle goes forward: made in ``cellctl.pick``, placed by
``cellctl.production``, never back.

One production cycle (count 1, no overlap) runs on the in-process virtual production cell while a
profile hook (``threading.setprofile``) follows the run's own thread (``production-<run id>``) and
records, for every Python call, the *room* it enters: a package of ``cellctl`` (``cellctl.pick``,
``cellctl.production``, ``cellctl.store``, ...) or, for the shared modules at ``cellctl``'s top
(``cellctl.mapping``, ``cellctl.motion``, ...), the module. A room is *left* when no frame of it is
on the thread's stack any more.

What it asserts, precisely:

- the rooms of the candidate's walk, ``cellctl.pick`` (where ``locate`` makes the candidate: the
  match, ``T_base_part``, the grasp) and ``cellctl.production`` (which chooses, picks, places and
  records it), are each entered in one visit: once left, neither is entered again during the cycle
  (``cellctl.production`` is never left: the run is production's; ``cellctl.pick`` is visited once,
  for the picture, and nothing of production comes back into it to compute a pose again, to fold a
  yaw, to read a place slot or to format a record);
- the walk between the two packages is forward: the sequence of the candidate's rooms is
  ``production -> pick -> production`` with the pick visit nested in production's call (one
  return, no second entry).

The shared modules at ``cellctl``'s top and the store are generic helpers (the audited move is
entered once per move, the mapping once per point): they are recorded and printed, not held.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

from tests.production.test_located_place import TAUGHT_AT, scene, teach_located_place
from tests.support.app import AppCell, in_process_cell
from tests.support.production_cell import production_config, teach_recipe, wait_ended

PACKAGES = ("pick", "production", "store", "plc", "routines", "api", "cli")
WALK = ("cellctl.pick", "cellctl.production")
"""The rooms a candidate goes through, in order."""


def room_of(module: str) -> str | None:
    """The room of a module: ``cellctl.<package>`` or a top-level ``cellctl.<module>``; None outside cellctl."""
    parts = module.split(".")
    if parts[0] != "cellctl" or len(parts) < 2:
        return None
    return f"cellctl.{parts[1]}"


class Walk:
    """Room entries of one thread (its name a regular expression), with re-entries after a room was left."""

    def __init__(self, thread_name: str) -> None:
        self.name = re.compile(thread_name)
        self.stack: list[str | None] = []
        self.left: set[str] = set()
        self.entries: list[str] = []
        self.reentered: list[str] = []
        self.lock = threading.Lock()

    def profile(self, frame: FrameType, event: str, arg: Any) -> None:
        if not self.name.fullmatch(threading.current_thread().name):
            return
        if event == "call":
            room = room_of(frame.f_globals.get("__name__", ""))
            if room is not None and room not in self.stack:
                self.entries.append(room)
                if room in self.left:
                    self.reentered.append(room)
                self.left.discard(room)
            self.stack.append(room)
        elif event == "return" and self.stack:
            room = self.stack.pop()
            if room is not None and room not in self.stack:
                self.left.add(room)


def walk_one_cycle(cell: AppCell, recipe_id: int = 1) -> Walk:
    """One production cycle (count 1, no overlap) of ``recipe_id`` under the profile hook."""
    http = cell.http()
    walk = Walk(r"production-\d+")  # the run's own thread (not its writer's)
    threading.setprofile(walk.profile)
    try:
        r = http.post("/production/start", json={"recipe_id": recipe_id, "count": 1, "overlap": False})
        assert r.status_code == 202, r.text
        end = wait_ended(http)
    finally:
        threading.setprofile(None)  # type: ignore[arg-type]
    assert end["ended_because"] == "count_reached" and end["counters"]["placed"] == 1, end
    # the run thread's last frames return after the state is stored: let them finish
    deadline = time.monotonic() + 10
    while any(t.name.startswith("production-") for t in threading.enumerate()) and time.monotonic() < deadline:
        time.sleep(0.05)
    sys.stdout.write(f"room entries of the run thread ({len(walk.entries)}): {walk.entries}\n")
    return walk


def assert_forward(walk: Walk) -> None:
    walked = [room for room in walk.entries if room in WALK]
    assert walked == ["cellctl.production", "cellctl.pick"], walked  # production, then one visit to pick
    assert not [room for room in walk.reentered if room in WALK], walk.reentered  # production never left mid-cycle


def test_one_candidate_walks_forward_through_a_production_cycle(tmp_path: Path) -> None:
    config = production_config(tmp_path, count=2, time_scale=0.2)
    with in_process_cell(tmp_path, config) as cell:
        teach_recipe(cell.http())
        walk = walk_one_cycle(cell)
    assert_forward(walk)


def test_a_located_place_is_found_in_the_same_visit(tmp_path: Path) -> None:
    """A recipe whose place is a fixture found by vision: the fixture is found by ``locate`` with the parts
    (``cellctl.pick.fixture``), so production does not come back into ``cellctl.pick`` for it."""
    config = production_config(tmp_path, count=2, time_scale=0.2, scene=scene(TAUGHT_AT))
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        recipe = teach_recipe(http)
        recipe["place"] = teach_located_place(cell)
        assert http.post("/recipes", json={"recipe_id": 2, "recipe": recipe}).status_code == 201
        walk = walk_one_cycle(cell, recipe_id=2)
    assert_forward(walk)
