"""The Machine Vision state machines' rules (cellctl.plc.opcua_mv.states), without a server, and the
result store's filter and keep-the-last-100 rule."""

from __future__ import annotations

from datetime import UTC, datetime

from cellctl.plc.opcua_mv.results import KEEP, Result, ResultStore
from cellctl.plc.opcua_mv.states import SYSTEM_STANDBY, SYSTEM_UNSCHEDULED_DOWN, VisionModel

LATCHED = "robot robot0 is latched by a Stop"


def test_the_vision_state_follows_start_up_halt_and_the_cell() -> None:
    m = VisionModel()
    assert m.vision_state(None) == "Preoperational" and m.auto_state(None) is None
    m.starting = False
    assert m.vision_state(None) == "Operational" and m.system_state(None) == (SYSTEM_STANDBY, "ready")
    assert m.vision_state(LATCHED) == "Error" and m.system_state(LATCHED) == (SYSTEM_UNSCHEDULED_DOWN, LATCHED)
    m.halted = True
    assert m.vision_state(None) == "Halted" and m.vision_state(LATCHED) == "Halted"


def test_the_automatic_mode_follows_selection_recipe_and_jobs() -> None:
    m = VisionModel(starting=False)
    assert m.auto_state(None) is None
    m.automatic = True
    assert m.auto_state(None) == "Initialized"
    m.prepared = 1
    assert m.auto_state(None) == "Ready"
    m.job = "single"
    assert m.auto_state(None) == "SingleExecution" and m.system_state(None)[0] == 1
    m.job = "continuous"
    assert m.auto_state(LATCHED) == "ContinuousExecution"  # a run stopped by a latch shows until it has ended
    m.job = None
    assert m.auto_state(LATCHED) is None and m.auto_state(None) == "Ready"


def _result(n: int, job: str, state: int = 1) -> Result:
    return Result(f"result-{n}", job, 1, "camera-1/handeye-2", state, datetime.now(UTC), '{"picks":[]}')


def test_the_result_store_keeps_the_last_100_and_filters_them() -> None:
    store = ResultStore()
    for n in range(1, KEEP + 11):
        store.add(_result(n, "job-1" if n % 2 else "run-2", state=1 if n % 3 else 3))
    newest = store.newest_first()
    assert len(newest) == KEEP and newest[0].result_id == f"result-{KEEP + 10}" and store.get("result-10") is None
    run, complete = store.filtered(0, {"JobId": "run-2"}, 0, 0)
    assert complete and len(run) == KEEP // 2 and all(r.job_id == "run-2" for r in run)
    aborted, _ = store.filtered(3, {"JobId": None, "InternalRecipeId": "1"}, 0, 0)
    assert aborted and all(r.state == 3 for r in aborted)
    page, complete = store.filtered(0, {}, 10, 5)
    assert [r.result_id for r in page] == [r.result_id for r in newest[10:15]] and not complete
    assert store.filtered(0, {"InternalRecipeId": "2"}, 0, 0) == ([], True)
