"""``/metrics``: Prometheus text, token-protected, fed by requests, devices, routines and picks.

The HTTP tests run the virtual cell's app in this process behind FastAPI's TestClient
(``tests.support.app``: create_app with its lifespan), with a viewer and an engineer token in its
config; the in-process tests use real cells (simulated and
OpenCV video-file devices) and a real ``JobManager``.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from cellctl import metrics
from cellctl.auth import hash_token
from cellctl.cell import Cell
from cellctl.config import default_config_text, parse_config
from cellctl.jobs import JobCancelled, JobContext, JobManager
from cellctl.services import Services
from drivers.camera.sim import SimCamera, SimCameraSettings
from tests.support.app import AppCell, in_process_cell

VIEWER = "cct_test-viewer-token-0123456789"
ENGINEER = "cct_test-engineer-token-0123456789"


def write_config(path: Path) -> Path:
    data = yaml.safe_load(default_config_text())
    data["cell_id"] = "metrics-test"
    data["auth"]["tokens"] = [{"name": "viewer", "role": "viewer", "sha256": hash_token(VIEWER)},
                              {"name": "engineer", "role": "engineer", "sha256": hash_token(ENGINEER)}]
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppCell]:
    tmp = tmp_path_factory.mktemp("metrics")
    with in_process_cell(tmp, write_config(tmp / "cell.yaml"), token=ENGINEER) as app:
        yield app


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of a Prometheus text page, keyed by (name, sorted labels); fails on bad syntax."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def scrape(served: AppCell, token: str = VIEWER) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    r = served.client.get("/metrics", headers={"Authorization": f"Bearer {token}"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain")
    return samples(r.text)


def test_metrics_needs_a_token(served: AppCell) -> None:
    r = served.client.get("/metrics")
    assert r.status_code == 401
    assert r.json()["error"]["code"] == "unauthorized"
    r = served.client.get("/metrics", headers={"Authorization": "Bearer cct_not-a-token"})
    assert r.status_code == 401
    # the lowest role is enough
    assert ("cellctl_build_info", (("version", served.client.get("/health").json()["version"]),)) \
        in scrape(served, VIEWER)


def test_request_latency_is_per_route_template_and_status(served: AppCell) -> None:
    with served.http(ENGINEER) as c:
        for _ in range(3):
            assert c.get("/robots/robot0/state").status_code == 200
        assert c.get("/robots/nope/state").status_code == 404
        assert c.get("/no/such/path/42").status_code == 404
    m = scrape(served)
    key = ("cellctl_http_request_duration_seconds_count",
           (("method", "GET"), ("route", "/robots/{robot_id}/state"), ("status", "200")))
    assert m[key] >= 3
    assert m[(key[0], (("method", "GET"), ("route", "/robots/{robot_id}/state"), ("status", "404")))] >= 1
    assert m[(key[0], (("method", "GET"), ("route", "unmatched"), ("status", "404")))] >= 1
    sum_key = ("cellctl_http_request_duration_seconds_sum", key[1])
    assert 0 < m[sum_key] < 30
    routes = {dict(labels).get("route") for (name, labels) in m if name.startswith("cellctl_http_request")}
    assert not any(r and re.search(r"robot0|nope|42", r) for r in routes), routes  # never raw paths
    # the histogram's buckets are cumulative and end at the count
    inf = ("cellctl_http_request_duration_seconds_bucket", tuple(sorted((*key[1], ("le", "+Inf")))))
    assert m[inf] == m[key]


def test_device_gauges_of_the_virtual_cell(served: AppCell) -> None:
    m = scrape(served)
    assert m[("cellctl_robot_connected", (("robot", "robot0"),))] == 1.0
    assert m[("cellctl_device_available", (("category", "camera"), ("device", "cam0"), ("kind", "sim")))] == 1.0
    assert m[("cellctl_device_outages_total", (("category", "robot"), ("device", "robot0")))] == 0.0


def test_request_id_is_echoed_or_made(served: AppCell) -> None:
    r = served.client.get("/health", headers={"X-Request-Id": "plc-7.order:42"})
    assert r.headers["x-request-id"] == "plc-7.order:42"
    made = served.client.get("/health").headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", made)
    assert served.client.get("/health").headers["x-request-id"] != made
    # an id that is not a sane token is not echoed (it would end up in the logs): a new one is made
    r = served.client.get("/health", headers={"X-Request-Id": "a b; drop"})
    assert re.fullmatch(r"[0-9a-f]{32}", r.headers["x-request-id"])
    # errors carry it too
    r = served.client.get("/metrics", headers={"X-Request-Id": "denied-1"})
    assert r.status_code == 401 and r.headers["x-request-id"] == "denied-1"


def test_routine_outcomes_are_counted(served: AppCell) -> None:
    with served.http(ENGINEER) as c:
        # The virtual cell starts with no active calibration to verify (refused at once): add the true lens.
        assert c.post("/routines/verify", json={}).status_code == 409
        added = c.post("/calibrations", json=c.get("/sim/truth").json()["camera"])
        assert c.post(f"/calibrations/{added.json()['id']}/activate").status_code == 200
        r = c.post("/routines/verify", json={})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        deadline = time.monotonic() + 20
        while (job := c.get(f"/jobs/{job_id}").json())["state"] == "running":
            assert time.monotonic() < deadline, job
            time.sleep(0.1)
    assert job["state"] == "succeeded", job
    assert scrape(served)[("cellctl_routine_outcomes_total", (("routine", "verify"), ("state", "succeeded")))] >= 1


# -- in process ------------------------------------------------------------------------------------


def virtual_services(extra: dict[str, Any] | None = None) -> Services:
    data = yaml.safe_load(default_config_text())
    data.update(extra or {})
    config = parse_config(data, "test")
    return Services(config, Cell(config), None, JobManager())  # type: ignore[arg-type]  # no store needed


def test_two_apps_in_one_process_keep_separate_registries() -> None:
    a, b = metrics.CellMetrics(), metrics.CellMetrics()
    sa, sb = virtual_services(), virtual_services()
    metrics.attach(a, sa)
    metrics.attach(b, sb)
    try:
        metrics.observe_pick(0.120, [0.91, 0.75], source=sa)
        metrics.observe_pick(0.080, [], source=sb)
        ma, mb = samples(a.render().decode()), samples(b.render().decode())
        assert ma[("cellctl_pick_latency_seconds_count", ())] == 1
        assert ma[("cellctl_pick_latency_seconds_sum", ())] == pytest.approx(0.120)
        assert ma[("cellctl_pick_match_score_count", ())] == 2
        assert ma[("cellctl_pick_match_score_bucket", (("le", "0.8"),))] == 1  # 0.75 <= 0.8 < 0.91
        assert ma[("cellctl_picks_total", (("result", "found"),))] == 1
        assert mb[("cellctl_pick_latency_seconds_count", ())] == 1
        assert mb[("cellctl_picks_total", (("result", "none"),))] == 1
        assert ("cellctl_picks_total", (("result", "found"),)) not in mb
        # each service records in its own metrics (no module-level registry finds "every app")
        sa.metrics.observe_pick(0.5, [0.5])
        sb.metrics.observe_pick(0.5, [0.5])
        assert samples(a.render().decode())[("cellctl_pick_latency_seconds_count", ())] == 2
        assert samples(b.render().decode())[("cellctl_pick_latency_seconds_count", ())] == 2
    finally:
        metrics.detach(a)
        metrics.detach(b)
    metrics.observe_pick(0.5, [0.5], source=sa)  # detached: nowhere, and no error
    assert samples(a.render().decode())[("cellctl_pick_latency_seconds_count", ())] == 2


def test_job_manager_reports_every_outcome() -> None:
    m = metrics.CellMetrics()
    services = virtual_services()
    metrics.attach(m, services)
    jobs = services.jobs

    def ok(ctx: JobContext) -> dict[str, Any]:
        return {"fine": True}

    def bad(ctx: JobContext) -> dict[str, Any]:
        raise ValueError("the plate is not seen")

    def cancelled(ctx: JobContext) -> dict[str, Any]:
        raise JobCancelled("cancelled on request")

    try:
        for name, fn in (("capture", ok), ("capture", ok), ("capture", bad), ("verify", cancelled)):
            jobs.join(jobs.start(name, fn, {}, "test").id, timeout_s=10)
        got = samples(m.render().decode())
        assert got[("cellctl_routine_outcomes_total", (("routine", "capture"), ("state", "succeeded")))] == 2
        assert got[("cellctl_routine_outcomes_total", (("routine", "capture"), ("state", "failed")))] == 1
        assert got[("cellctl_routine_outcomes_total", (("routine", "verify"), ("state", "cancelled")))] == 1
        # another manager's jobs are not this app's
        other = JobManager()
        other.join(other.start("capture", ok, {}, "test").id, timeout_s=10)
        got = samples(m.render().decode())
        assert got[("cellctl_routine_outcomes_total", (("routine", "capture"), ("state", "succeeded")))] == 2
    finally:
        metrics.detach(m)


def test_camera_frames_rate_and_outages_from_the_slots(tmp_path: Path) -> None:
    video = tmp_path / "line.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 12.5, (64, 48))
    for k in range(10):
        writer.write(np.full((48, 64, 3), 20 * k, np.uint8))
    writer.release()
    services = virtual_services({"cameras": {"line": {"kind": "opencv", "settings": {"source": str(video)}}}})
    m = metrics.CellMetrics()
    metrics.attach(m, services)
    cell = services.cell
    try:
        cell.open_all()
        for _ in range(4):
            cell.camera("line").device.grab()
        got = samples(m.render().decode())
        assert got[("cellctl_camera_frames_total", (("camera", "line"),))] == 4
        assert got[("cellctl_camera_frame_rate_hz", (("camera", "line"),))] == pytest.approx(12.5)
        assert got[("cellctl_device_available", (("category", "camera"), ("device", "line"),
                                                 ("kind", "opencv")))] == 1
        assert got[("cellctl_robot_connected", (("robot", "robot0"),))] == 1
        # the robot is lost: the gauge drops and the outage is counted
        cell.robot("robot0").report_failure(ConnectionError("cable pulled"))
        got = samples(m.render().decode())
        assert got[("cellctl_robot_connected", (("robot", "robot0"),))] == 0
        assert got[("cellctl_device_outages_total", (("category", "robot"), ("device", "robot0")))] == 1
        assert ("cellctl_camera_frame_rate_hz", (("camera", "line"),)) in got
        # a closed camera is unavailable and reports no rate (settings() is only asked of open devices)
        cell.close()
        got = samples(m.render().decode())
        assert got[("cellctl_device_available", (("category", "camera"), ("device", "line"),
                                                 ("kind", "opencv")))] == 0
        assert ("cellctl_camera_frame_rate_hz", (("camera", "line"),)) not in got
    finally:
        metrics.detach(m)
        cell.close()


class StuckSettingsCamera(SimCamera):
    """The simulated camera with a control channel that stops answering ``settings()``."""

    release = threading.Event()

    def settings(self) -> dict[str, Any]:
        self.release.wait(30)
        return {"frame_rate_hz": 5.0}


def test_a_camera_that_stops_answering_does_not_stall_the_scrape() -> None:
    services = virtual_services()
    slot = services.cell.camera("cam0")
    settings = SimCameraSettings.model_validate(services.config.cameras["cam0"].settings)
    slot.device = StuckSettingsCamera("cam0", settings)
    m = metrics.CellMetrics()
    metrics.attach(m, services)
    try:
        services.cell.open_all()
        for _ in range(2):  # the second scrape does not start another call while one is stuck
            t0 = time.perf_counter()
            got = samples(m.render().decode())
            assert time.perf_counter() - t0 < metrics.SETTINGS_TIMEOUT_S + 1.0
            assert ("cellctl_camera_frame_rate_hz", (("camera", "cam0"),)) not in got
            assert got[("cellctl_robot_connected", (("robot", "robot0"),))] == 1
        assert sum(t.name == "metrics-cam0" for t in threading.enumerate()) == 1
        StuckSettingsCamera.release.set()  # the camera answers again
        deadline = time.monotonic() + 5
        while ("cellctl_camera_frame_rate_hz", (("camera", "cam0"),)) not in (got := samples(m.render().decode())):
            assert time.monotonic() < deadline
        assert got[("cellctl_camera_frame_rate_hz", (("camera", "cam0"),))] == 5.0
    finally:
        StuckSettingsCamera.release.set()
        metrics.detach(m)
        services.cell.close()
