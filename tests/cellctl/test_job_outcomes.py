"""How a routine's job ends and what it says: a config error answered at once (409/422, no job),
a failure that says what failed first and then what was done (the robot "stopped" only when the
routine moved it), and a NOT OK verdict: state ``succeeded`` with ``verdict_ok: false`` and
``cellctl job run --follow`` exiting 3."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from cellctl.jobs import JobContext, JobManager
from cellctl.routines.common import RoutineError
from tests.conftest import Served, start_served, stop_served
from tests.support.cli import run_cli


def _ended(jobs: JobManager, job_id: str) -> Any:
    return jobs.join(job_id, timeout_s=30.0)


def test_a_failure_says_what_failed_then_what_was_done() -> None:
    jobs = JobManager()

    def never_moved(ctx: JobContext) -> dict[str, Any]:
        raise RoutineError("the plate is not seen (no marks); put it in view")

    def moved(ctx: JobContext) -> dict[str, Any]:
        ctx.moved = True
        raise RoutineError("hand-eye cannot be solved")

    a = _ended(jobs, jobs.start("x", never_moved, {}, "t").id)
    assert a.state == "failed"
    assert a.message == "failed: the plate is not seen (no marks); put it in view; the robot was not moved and " \
                        "nothing was stored"
    b = _ended(jobs, jobs.start("x", moved, {}, "t").id)
    assert b.message.startswith("failed: hand-eye cannot be solved; the robot was stopped")

    def waits(ctx: JobContext) -> dict[str, Any]:
        ctx.sleep(30.0)
        return {}

    c = jobs.start("x", waits, {}, "t")
    jobs.cancel(c.id)
    assert _ended(jobs, c.id).message == "cancelled on request; the robot was not moved and nothing was stored"
    assert a.public()["verdict_ok"] is None and b.public()["verdict_ok"] is None


def test_a_not_ok_verdict_is_its_own_outcome() -> None:
    jobs = JobManager()
    results: list[dict[str, Any]] = [
        {"calibration_id": 7, "verdict": {"ok": False, "problems": [{"code": "too_few_views"}]}},
        {"calibration_id": 8, "verdict": {"ok": True, "problems": []}}, {"passed": False}, {"n": 1}]

    def returning(result: dict[str, Any]) -> Callable[[JobContext], dict[str, Any]]:
        return lambda _ctx: result

    ended = [_ended(jobs, jobs.start("x", returning(r), {}, "t").id) for r in results]
    assert [j.state for j in ended] == ["succeeded"] * 4
    assert [j.public()["verdict_ok"] for j in ended] == [False, True, False, None]
    assert "NOT OK: too_few_views; stored as calibration 7 (not activated)" in ended[0].message
    assert ended[1].message == "done" and ended[3].message == "done"


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("outcomes"))
    try:
        yield s
    finally:
        stop_served(s)


def test_config_errors_are_answered_at_once(served: Served) -> None:
    with served.client() as http:
        before = len(http.get("/jobs").json())
        r = http.post("/routines/jog-to-mark", json={"tool_centre": True})
        assert r.status_code == 409 and r.json()["error"]["code"] == "wrong_setup"
        assert "eye-in-hand" in r.json()["error"]["message"] and "eye-to-hand" in r.json()["error"]["message"]
        r = http.post("/routines/jog-to-mark", json={"marks": 4, "tcp_mark": 9})
        assert r.status_code == 422 and "only 4 marks" in r.json()["error"]["message"]
        r = http.post("/routines/verify", json={"target": "nosuch"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "unknown_target"
        assert "plate" in r.json()["error"]["message"]  # the configured ones are named
        r = http.post("/routines/handeye-capture", json={"camera_id": "cam9"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "unknown_camera"
        r = http.post("/routines/handeye-capture", json={"stations": 30, "max_stations": 20})
        assert r.status_code == 422 and "max_stations" in r.json()["error"]["message"]
        r = http.post("/routines/handeye-capture", json={})
        assert r.status_code == 409 and r.json()["error"]["code"] == "no_active_calibration"
        assert "POST /calibrations" in r.json()["error"]["message"]
        assert len(http.get("/jobs").json()) == before  # no job was started
        assert http.get("/robots/robot0/motion").json()["owner"] is None  # nor was the robot taken


def test_job_run_exits_3_on_a_not_ok_verdict(served: Served) -> None:
    with served.client() as http:
        camera = http.get("/sim/truth").json()["camera"]
        added = http.post("/calibrations", json=camera, params={"note": "truth"})
        assert added.status_code == 201, added.text
        assert http.post(f"/calibrations/{added.json()['id']}/activate").status_code == 200
    common = ("--follow", "--url", served.base_url, "--token", served.token)
    r = run_cli("job", "run", "verify", "--param", "tolerance_px=0.0001", *common)
    assert r.returncode == 3, r.stderr
    job = json.loads(r.stdout)
    assert job["state"] == "succeeded" and job["verdict_ok"] is False and job["result"]["passed"] is False
    assert "NOT OK" in r.stderr
    r = run_cli("job", "run", "verify", "--param", "tolerance_px=5", *common)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["verdict_ok"] is True
