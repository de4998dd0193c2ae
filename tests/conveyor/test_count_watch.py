"""A belt run watches the encoder's count while the arm moves (``BeltMeetingRun._watch_count``, every
``WATCH_S``): a count that jumps mid-cycle ends the run failed with the jump, the arm halted in that move, not
seconds later at the next plan (when a read that late took the jump for an ordinary belt: the run went on with
its parts 400 mm off). One in-process conveyor cell (``tests.support.app``), the belt's truth calibration."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from typing import Any

import pytest

from cellctl.production.belt_meeting import WATCH_S
from drivers.robot.sim import SimRobot
from drivers.sim.world import SimWorld, world_for
from tests.support.app import AppCell, in_process_cell
from tests.support.conveyor_cell import conveyor_config, set_speed, teach_belt_recipe, wait_ended

SEEN_WITHIN_S = 0.5
"""The jump is read within this of it (the reads either side of it this far apart at most): ``WATCH_S`` and a
loaded machine's delays."""
ENDED_WITHIN_S = 5.0
"""The run ends within this of the jump: seen, the arm halted, then the run's end as after any fault (the vision
thread's picture in progress finishes first: ~1 s at a load of 17 on 2 cores; the slot's claim settled, the
store's writes). 0.03-0.16 s at load 2-4, 0.64 s once at load 6."""


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, SimWorld]]:
    tmp = tmp_path_factory.mktemp("count_watch")
    cfg = conveyor_config(tmp)
    with in_process_cell(tmp, cfg) as app:
        teach_belt_recipe(app.http())
        yield app, world_for(str(tmp / "scene.yaml"))


PLACE_PHASES = ("carrying", "over_slot", "releasing", "leaving")
"""The phases of a cycle from its carry to its place's end: no count read of the run's own thread in them."""


def test_a_count_that_jumps_while_the_arm_carries_a_part_ends_the_run_failed_in_that_cycle(
        cell: tuple[AppCell, SimWorld], monkeypatch: pytest.MonkeyPatch) -> None:
    """The count jumps as the arm starts to carry its first part to the slot (injected on the run's thread as
    that move begins: the run's thread then blocked in the move, no count read of its own until the next
    cycle's plan): the jump is read within ``SEEN_WITHIN_S`` and the run ends ``failed`` naming it, in that
    cycle's carry or place (nothing placed), not at the next plan. Without the watcher the run went on: running
    30 s after the jump."""
    app, world = cell
    http = app.http()
    assert world.belt is not None
    belt = world.belt
    manager = app.client.app.state.services.production  # type: ignore[attr-defined]
    jumped_at: list[float] = []
    travel = SimRobot._travel

    def jump_as_the_carry_starts(robot: SimRobot, *args: Any, **kwargs: Any) -> None:
        if not jumped_at and manager.run("robot0").phase == "carrying":
            jumped_at.append(time.monotonic())
            belt.simulate_count_jump(4000)
        travel(robot, *args, **kwargs)

    monkeypatch.setattr(SimRobot, "_travel", jump_as_the_carry_starts)
    set_speed(http, 100.0)
    assert http.post("/production/start", json={"recipe_id": 1, "count": 0}).status_code == 202
    try:
        st = http.get("/production").json()
        deadline = time.monotonic() + 60.0
        while st["ended_because"] is None and time.monotonic() < deadline and (
                not jumped_at or time.monotonic() - jumped_at[0] < ENDED_WITHIN_S):
            time.sleep(0.005)
            st = http.get("/production").json()
        took_s = time.monotonic() - jumped_at[0] if jumped_at else None
    finally:
        if http.get("/production").json()["ended_because"] is None:
            http.post("/production/stop")
            wait_ended(http, 30.0)
        belt.clear_faults()
    assert took_s is not None, f"no part was carried: {st}"
    assert st["state"] == "failed", st
    m = re.search(r"jumped by (\d+) ticks in (\d+) ms", st["error"] or "")
    assert m is not None, st
    jump, ms = int(m.group(1)), int(m.group(2))
    assert abs(jump - 4000 - ms) <= 20, st  # the jump and the belt's travel (100 mm/s: 1 tick a ms) between reads
    assert ms <= 1e3 * SEEN_WITHIN_S, f"the reads either side of the jump {ms} ms apart (every {WATCH_S} s): {st}"
    assert st["phase"] in PLACE_PHASES and st["counters"]["placed"] == 0, st  # that cycle's, not the next plan's
    assert took_s <= ENDED_WITHIN_S, f"the run ended {took_s:.2f} s after the jump: {st}"
