"""The jog-to-mark wizard shows the N-point verdict at the end: OK with its figures for good
records, NOT OK with the problem and its advice when a mark was recorded off its centre.

The test plays the operator through the page's own job: for each mark the page asks for, it
records the mark's true robot position (from the virtual cell's truth) in the record body."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from calibration import geometry as g
from calibration.targets import target_from_dict
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.ui.conftest import SHOTS

expect.set_options(timeout=60_000)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("wizverdict"))
    try:
        yield s
    finally:
        stop_served(s)


@pytest.fixture(scope="module")
def marks_mm() -> dict[int, np.ndarray]:
    truth = json.loads(run_cellctl("sim", "truth", check=True).stdout)
    plate = truth["targets"]["plate"]
    pts = target_from_dict(plate["target"]).points()
    xyz = g.transform_points(np.array(plate["T_base_target"]), pts.xyz_m) * 1e3
    return {int(i): xyz[k, :2] for k, i in enumerate(pts.ids)}


def _run(page: Page, served: Served, marks_mm: dict[int, np.ndarray], off_mm: dict[int, tuple[float, float]]) -> None:
    """Start the wizard with 9 marks and record each at its true position (plus ``off_mm`` by step)."""
    page.select_option("#wiz-marks", "9")
    page.click("#wiz-start-button")
    expect(page.locator("#wiz-record")).to_be_enabled()
    job_id = page.locator("#wiz-run").get_attribute("data-job-id")
    with served.client() as http:
        for step in range(1, 10):
            deadline = time.monotonic() + 30
            while ((job := http.get(f"/jobs/{job_id}").json())["waiting_for"] or {}).get("step") != step:
                assert job["state"] == "running", job["error"]
                assert time.monotonic() < deadline
                time.sleep(0.1)
            xy = marks_mm[job["waiting_for"]["mark_id"]] + np.array(off_mm.get(step, (0.0, 0.0)))
            r = http.post(f"/jobs/{job_id}/record", json={"x_mm": float(xy[0]), "y_mm": float(xy[1])})
            assert r.status_code == 200, r.text
    expect(page.locator("#wiz-result")).to_be_visible()


def test_the_wizard_shows_the_verdict(served: Served, browser: Browser, marks_mm: dict[int, Any]) -> None:
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.goto(served.base_url + "/")
    page.fill("#token", served.token)
    page.click("#login-button")
    expect(page.locator("#who-role")).to_have_text("engineer")
    page.click("#tabs button[data-tab=wizard]")
    expect(page.locator("#wiz-tool-centre")).to_be_visible()  # the engineer may ask for the tool centre
    _run(page, served, marks_mm, {})
    verdict = page.locator("#wiz-verdict")
    expect(verdict).to_have_attribute("data-ok", "true")
    expect(verdict.locator(".verdict-ok")).to_contain_text("Verdict: OK")
    expect(verdict).to_contain_text("leave-one-out RMS")
    page.screenshot(path=str(SHOTS / "wizard-verdict-ok.png"), full_page=True)

    page.click("#wiz-again")
    expect(page.locator("#wiz-verdict")).to_be_empty()
    _run(page, served, marks_mm, {7: (1.6, -1.1)})  # mark 7 recorded 1.9 mm off its centre
    verdict = page.locator("#wiz-verdict")
    expect(verdict).to_have_attribute("data-ok", "false")
    expect(verdict.locator(".verdict-bad")).to_contain_text("Verdict: NOT OK")
    problem = verdict.locator("li.problem")
    expect(problem).to_contain_text("loo_too_large")
    expect(problem).to_contain_text("worst: mark 7")
    expect(problem).to_contain_text("re-record")
    page.screenshot(path=str(SHOTS / "wizard-verdict-not-ok.png"), full_page=True)


def test_the_tool_centre_needs_a_fixed_camera(served: Served) -> None:
    """The built-in cell's camera rides on the tool: the turn is refused at once (409, no job), before it moves."""
    with served.client() as http:
        r = http.post("/routines/jog-to-mark", json={"tool_centre": True})
    assert r.status_code == 409 and r.json()["error"]["code"] == "wrong_setup", r.text
    assert "needs a fixed camera" in r.json()["error"]["message"]
