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


def _wait_phase(http: Any, phase: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = http.get("/production").json()
        assert st["ended_because"] is None, st
        if st.get("phase") == phase:
            return
        time.sleep(0.005)
    raise TimeoutError(f"phase {phase} not reached: {http.get('/production').json()}")


def test_a_count_that_jumps_while_the_arm_carries_a_part_ends_the_run_failed_in_that_move(
        cell: tuple[AppCell, SimWorld]) -> None:
    """The jump comes as the arm starts carrying a part to its slot (the run's thread blocked in that move, no
    count read of its own until the next cycle): the jump is read within ``SEEN_WITHIN_S`` and the run ends
    ``failed`` naming it, still in the phase ``carrying`` (the move halted, not the next plan's read). On main
    (no watcher) the run went on: running 30 s after the jump."""
    app, world = cell
    http = app.http()
    assert world.belt is not None
    set_speed(http, 100.0)
    assert http.post("/production/start", json={"recipe_id": 1, "count": 0}).status_code == 202
    try:
        _wait_phase(http, "carrying")
        t_jump = time.monotonic()
        world.belt.simulate_count_jump(4000)
        st = http.get("/production").json()
        while st["ended_because"] is None and time.monotonic() - t_jump < 30.0:
            time.sleep(0.005)
            st = http.get("/production").json()
        took_s = time.monotonic() - t_jump
    finally:
        if http.get("/production").json()["ended_because"] is None:
            http.post("/production/stop")
            wait_ended(http, 30.0)
        world.belt.clear_faults()
    assert st["state"] == "failed", st
    m = re.search(r"jumped by (\d+) ticks in (\d+) ms", st["error"] or "")
    assert m is not None, st
    jump, ms = int(m.group(1)), int(m.group(2))
    assert abs(jump - 4000 - ms) <= 20, st  # the jump and the belt's travel (100 mm/s: 1 tick a ms) between reads
    assert ms <= 1e3 * SEEN_WITHIN_S, f"the reads either side of the jump {ms} ms apart (every {WATCH_S} s): {st}"
    assert st["phase"] == "carrying", st  # ended in the move it came in, not at the next plan
    assert took_s <= ENDED_WITHIN_S, f"the run ended {took_s:.2f} s after the jump: {st}"
