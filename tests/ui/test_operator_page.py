"""The operator page end-to-end in headless Chromium (Debian's ``/usr/bin/chromium``, Playwright).

One ``cellctl serve`` of the virtual cell with an engineer and an operator token. The engineer
logs in, sees the camera and the robot, and runs the jog-to-mark wizard to completion: for each
highlighted mark the test plays the operator's hand (it jogs the robot onto the mark's true
position over the API) and clicks Record in the page; the page shows the residuals, and Activate
makes the calibration active. Then a pick test from the page. The operator sees no engineer
controls. Screenshots of the main views go to ``test-artifacts/screenshots/``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from calibration import geometry as g
from calibration.io import camera_from_json
from calibration.targets import target_from_dict
from cellctl.cli import main
from cellctl.config import default_config_text
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.ui.conftest import SHOTS

MARKS = 9
WAIT_MS = 60_000
expect.set_options(timeout=WAIT_MS)


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("ui")
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text())
    tokens: dict[str, str] = {}
    for role in ("operator", "engineer"):
        out = tmp / f"{role}.json"
        assert main(["token", "add", "--config", str(cfg), "--name", f"{role}-ui", "--role", role,
                     "--out", str(out)]) == 0
        tokens[role] = json.loads(out.read_text())["token"]
    served = start_served(tmp, config=cfg, token=tokens["engineer"])
    try:
        yield served, tokens
    finally:
        stop_served(served)


@pytest.fixture(scope="module")
def truth() -> dict[str, Any]:
    out = run_cellctl("sim", "truth", check=True).stdout
    return dict(json.loads(out))


def new_page(browser: Browser, served: Served) -> tuple[Page, list[str]]:
    """A fresh tab on the operator page, and the list its uncaught script errors go to."""
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    page.set_default_timeout(WAIT_MS)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(served.base_url + "/")
    return page, errors


def log_in(page: Page, token: str) -> None:
    page.fill("#token", token)
    page.click("#login-button")
    expect(page.locator("#main-view")).to_be_visible()


def test_page_and_static_files_are_open_and_the_api_is_not(cell: tuple[Served, dict[str, str]]) -> None:
    served, tokens = cell
    with httpx.Client(base_url=served.base_url, timeout=10) as http:
        r = http.get("/")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert '<script type="module" src="/ui/main.js">' in r.text
        modules = ("main.js", "core.js", "live.js", "calib.js", "wizard.js", "routines.js", "pick.js")
        for name, kind in (*((m, "text/javascript") for m in modules), ("style.css", "text/css")):
            r = http.get(f"/ui/{name}")
            assert r.status_code == 200 and r.headers["content-type"].startswith(kind), name
        for bad in ("/ui/..%2Fapi%2Fapp.py", "/ui/.hidden", "/ui/nosuch.js", "/ui/ui.py"):
            assert http.get(bad).status_code == 404, bad
        assert http.get("/auth/whoami").status_code == 401
        r = http.get("/auth/whoami", headers={"Authorization": f"Bearer {tokens['operator']}"})
        assert r.json() == {"name": "operator-ui", "role": "operator"}
        assert "/auth/whoami" in http.get("/openapi.json").json()["paths"]


def jog_onto_mark(http: httpx.Client, truth: dict[str, Any], mark_id: int) -> None:
    """The operator's hand: the tool tip 5 mm above the mark's true position, pointing down."""
    plate = truth["targets"]["plate"]
    pts = target_from_dict(plate["target"]).points()
    p_base = g.transform_points(np.array(plate["T_base_target"]), pts.xyz_m[list(pts.ids).index(mark_id)])[0]
    pose = {"x_m": p_base[0], "y_m": p_base[1], "z_m": p_base[2] + 0.005, "rx_rad": math.pi, "ry_rad": 0.0,
            "rz_rad": 0.0}
    r = http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.25})
    assert r.status_code == 200, r.text


def run_wizard(page: Page, http: httpx.Client, truth: dict[str, Any], marks: int,
               midway_shot: str | None = None) -> list[int]:
    """Start the wizard in the page; for each mark it highlights, jog onto it and click Record."""
    page.click("#tabs button[data-tab=wizard]")
    page.select_option("#wiz-marks", str(marks))
    page.click("#wiz-start-button")
    recorded: list[int] = []
    for step in range(1, marks + 1):
        expect(page.locator("#wiz-run")).to_have_attribute("data-step", str(step))
        expect(page.locator("#wiz-record")).to_be_enabled()
        expect(page.locator("#wiz-step")).to_have_text(f"Mark {step} of {marks}")
        expect(page.locator("#wiz-instruction")).to_contain_text(f"Jog the tool to mark {step}")
        mark_id = int(page.get_attribute("#wiz-run", "data-mark-id") or -1)
        job_id = page.get_attribute("#wiz-run", "data-job-id")
        # The page highlights the mark the routine is waiting for.
        assert http.get(f"/jobs/{job_id}").json()["waiting_for"]["mark_id"] == mark_id
        expect(page.locator("#wiz-marks-table tbody tr")).to_have_count(marks)
        expect(page.locator("#wiz-marks-table tbody tr.current td").nth(1)).to_have_text(str(mark_id))
        expect(page.locator("#wiz-marks-table tbody tr.done")).to_have_count(step - 1)
        jog_onto_mark(http, truth, mark_id)
        if midway_shot and step == (marks + 1) // 2:
            page.screenshot(path=str(SHOTS / midway_shot), full_page=True)
        page.click("#wiz-record")
        recorded.append(mark_id)
    assert len(set(recorded)) == marks
    expect(page.locator("#wiz-result")).to_be_visible()
    return recorded


def test_engineer_runs_the_wizard_to_completion_and_activates(
        cell: tuple[Served, dict[str, str]], browser: Browser, truth: dict[str, Any]) -> None:
    served, tokens = cell
    page, errors = new_page(browser, served)
    http = served.client(tokens["engineer"], timeout_s=60)
    home = http.get("/robots/robot0/state").json()["T_base_tool"]

    # Login: a wrong token is refused with a message; the right one opens the page.
    expect(page.locator("#login-view")).to_be_visible()
    page.screenshot(path=str(SHOTS / "login.png"), full_page=True)
    page.fill("#token", "cct_not-a-token")
    page.click("#login-button")
    expect(page.locator("#login-error")).to_contain_text("not accepted")
    log_in(page, tokens["engineer"])
    expect(page.locator("#who-role")).to_have_text("engineer")

    # Live view: a camera frame is drawn and the robot state matches the robot.
    canvas = page.locator("#live-canvas")
    expect(canvas).to_have_attribute("data-frame-id", re.compile(r"^[0-9]+$"))
    assert (canvas.get_attribute("width"), canvas.get_attribute("height")) == ("1280", "960")
    expect(page.locator("#rs-x")).to_have_text(f"{home[0][3] * 1e3:.2f}")
    expect(page.locator("#rs-z")).to_have_text(f"{home[2][3] * 1e3:.2f}")
    expect(page.locator("#rs-mode")).to_have_text("running")
    expect(page.locator("#active-summary")).to_have_text("none active")
    page.screenshot(path=str(SHOTS / "live.png"), full_page=True)

    # The jog-to-mark wizard, every mark recorded through the page.
    recorded = run_wizard(page, http, truth, MARKS, midway_shot="wizard-midway.png")

    # The result: residuals per mark, then Activate.
    expect(page.locator("#wiz-result")).to_be_visible()
    expect(page.locator("#wiz-residuals tbody tr")).to_have_count(MARKS)
    rms_mm = float(page.get_attribute("#wiz-summary", "data-rms-mm") or "nan")
    # No camera calibration is active, so the lens distortion stays in the residuals (about 0.1 mm here;
    # tests/cellctl/test_routines_e2e.py checks the fit with the lens corrected).
    assert 0 < rms_mm < 0.3
    shown = [int(t) for t in page.locator("#wiz-residuals tbody tr td:nth-child(2)").all_inner_texts()]
    assert shown == recorded
    cal_id = int(page.get_attribute("#wiz-result", "data-calibration-id") or -1)
    residuals = http.get(f"/calibrations/{cal_id}").json()["result"]["residuals_mm"]
    shown_res = page.locator("#wiz-residuals tbody tr td:nth-child(7)").all_inner_texts()
    assert shown_res == [f"{r:.4f}" for r in residuals]
    assert not [c for c in http.get("/calibrations").json() if c["active"]]
    page.screenshot(path=str(SHOTS / "wizard-result.png"), full_page=True)
    page.click("#wiz-activate")
    expect(page.locator("#wiz-activated")).to_contain_text(f"#{cal_id} is now active")
    active = [c for c in http.get("/calibrations").json() if c["active"]]
    assert [(c["id"], c["kind"]) for c in active] == [(cal_id, "npoint")]

    # The calibrations view shows it active, with its report.
    page.click("#tabs button[data-tab=calib]")
    row = page.locator(f"#calib-table tbody tr[data-id='{cal_id}']")
    expect(row.locator("td.state")).to_have_text("active")
    row.locator("button.report").click()
    expect(page.frame_locator("#report-frame").locator("h1")).to_contain_text(f"npoint calibration {cal_id}")
    page.screenshot(path=str(SHOTS / "calibrations.png"), full_page=True)

    # Pick test from the page through the new calibration: back to its capture pose, teach the bracket
    # (the engineer's set-up, over the API), then the operator's button.
    assert http.post("/robots/robot0/move", json={"T_base_tool": home, "speed_m_s": 0.25}).status_code == 200
    camera = camera_from_json(truth["camera"], "truth")
    part = next(p for p in truth["parts"] if p["name"] == "bracket")
    p_cam = g.transform_points(g.invert(np.array(truth["T_base_cam"])),
                               [part["x_mm"] * 1e-3, part["y_mm"] * 1e-3, part["z_mm"] * 1e-3])
    u, v = camera.project(p_cam)[0]
    r = http.post("/pick/teach", json={"roi": [u - 100, v - 100, 200, 200], "name": "bracket"})
    assert r.status_code == 200, r.text
    r = http.post("/recipes", json={"recipe_id": 7, "recipe": {"name": "bracket", "models": [r.json()],
                                                              "plane_z_mm": 0.0, "grasp_z_mm": 5.0}})
    assert r.status_code == 201, r.text
    page.click("#tabs button[data-tab=pick]")
    expect(page.locator("#pick-recipes")).to_contain_text("7 bracket")
    page.select_option("#pick-recipe", "7")
    page.click("#pick-button")
    expect(page.locator("#pick-table")).to_be_visible()
    expect(page.locator("#pick-image")).to_be_visible()
    first = page.locator("#pick-table tbody tr").first.locator("td").all_inner_texts()
    assert first[1] == "bracket" and first[-1] == "yes"
    x_mm, y_mm = float(first[5]), float(first[6])
    # Through an n-point map fitted without lens correction, away from the marks: a few mm.
    assert math.hypot(x_mm - part["x_mm"], y_mm - part["y_mm"]) < 5.0, (x_mm, y_mm)
    page.screenshot(path=str(SHOTS / "pick.png"), full_page=True)
    # The live view draws the last pick's matches.
    page.click("#tabs button[data-tab=live]")
    expect(page.locator("#live-status")).to_contain_text("last pick: ")
    page.wait_for_timeout(300)
    page.screenshot(path=str(SHOTS / "live-with-pick.png"), full_page=True)
    assert errors == []
    http.close()
    page.close()


def test_engineer_follows_a_capture_routine_over_sse(cell: tuple[Served, dict[str, str]], browser: Browser) -> None:
    served, tokens = cell
    page, errors = new_page(browser, served)
    log_in(page, tokens["engineer"])
    page.click("#tabs button[data-tab=routines]")
    card = page.locator(".routine[data-routine=intrinsics-capture]")
    card.locator("input[name=views]").fill("6")  # the form is generated from the routine's parameter schema
    card.locator("input[name=max_views]").fill("6")
    card.locator("button.start").click()
    expect(card.locator(".log li").nth(2)).to_contain_text("view ", timeout=90_000)
    page.screenshot(path=str(SHOTS / "routine-progress.png"), full_page=True)
    expect(card).to_have_attribute("data-state", "succeeded", timeout=120_000)
    log = card.locator(".log li").all_inner_texts()
    # Every event the routine emitted reached the page, in order, through the streamed fetch.
    with served.client(tokens["engineer"]) as http:
        job = http.get(f"/jobs/{card.get_attribute('data-job-id')}").json()
        assert job["state"] == "succeeded"
        lines = http.get(f"/jobs/{job['id']}/events").text.splitlines()
    messages = [json.loads(ln[len("data: "):]) for ln in lines if ln.startswith("data: ")]
    # The end line is the job's message: "done", or with 6 views "done, but the verdict is NOT OK: ..."
    expected = [m["message"] for m in messages if "progress" in m] + [f"succeeded: {job['message']}"]
    assert log[1:] == expected[-(len(log) - 1):]
    assert any(m.startswith("calibrating ") for m in log)
    result = dict(zip(card.locator(".result th").all_inner_texts(), card.locator(".result td").all_inner_texts(),
                      strict=True))
    assert result["calibration"] == f"#{job['result']['calibration_id']}"
    assert result["views used"] == str(job["result"]["views_used"])
    assert result["verdict"].startswith("OK" if job["result"]["verdict"]["ok"] else "NOT OK")
    expect(card.locator("button.activate")).to_be_visible()
    page.screenshot(path=str(SHOTS / "routine-done.png"), full_page=True)
    assert errors == []
    page.close()


def test_operator_is_not_offered_engineer_controls(cell: tuple[Served, dict[str, str]], browser: Browser,
                                                  truth: dict[str, Any]) -> None:
    served, tokens = cell
    page, errors = new_page(browser, served)
    log_in(page, tokens["operator"])
    expect(page.locator("#who-role")).to_have_text("operator")
    # An operator runs jog-to-mark, verify and the pick test, and may stop the robot...
    for tab in ("wizard", "routines", "pick"):
        expect(page.locator(f"#tabs button[data-tab={tab}]")).to_be_visible()
    expect(page.locator("#robot-stop")).to_be_visible()
    page.click("#tabs button[data-tab=routines]")
    expect(page.locator(".routine[data-routine=verify] button.start")).to_be_visible()
    # ...but neither captures (they move the robot) nor activation nor robot moves from a pick.
    for routine in ("intrinsics-capture", "handeye-capture"):
        expect(page.locator(f".routine[data-routine={routine}]")).to_be_hidden()
    page.screenshot(path=str(SHOTS / "operator-routines.png"), full_page=True)
    page.click("#tabs button[data-tab=pick]")
    expect(page.locator("#pick-move")).to_be_hidden()
    # The operator runs the wizard (the engineer's pendant jogs): the result has no Activate.
    http = served.client(tokens["engineer"], timeout_s=60)
    run_wizard(page, http, truth, 4)
    expect(page.locator("#wiz-residuals tbody tr")).to_have_count(4)
    expect(page.locator("#wiz-again")).to_be_visible()
    expect(page.locator("#wiz-activate")).to_be_hidden()
    page.screenshot(path=str(SHOTS / "operator-wizard-result.png"), full_page=True)
    cal_id = page.get_attribute("#wiz-result", "data-calibration-id")
    assert http.get(f"/calibrations/{cal_id}").json()["active"] is False
    # The new calibration is listed with its report but, for the operator, without Activate...
    page.click("#tabs button[data-tab=calib]")
    row = page.locator(f"#calib-table tbody tr[data-id='{cal_id}']")
    expect(row.locator("button.report")).to_be_visible()
    expect(row.locator("td.state")).to_have_text("")
    expect(page.locator("#calib-table button.activate")).to_have_count(0)
    # ...while an engineer is offered it on the same row.
    eng, _ = new_page(browser, served)
    log_in(eng, tokens["engineer"])
    eng.click("#tabs button[data-tab=calib]")
    expect(eng.locator(f"#calib-table tbody tr[data-id='{cal_id}'] button.activate")).to_be_visible()
    eng.close()
    http.close()
    # The token survives a reload (sessionStorage) and logging out forgets it.
    page.reload()
    expect(page.locator("#who-role")).to_have_text("operator")
    page.click("#logout")
    expect(page.locator("#login-view")).to_be_visible()
    page.reload()
    expect(page.locator("#login-view")).to_be_visible()
    assert errors == []
    page.close()


def test_stop_from_the_page_latches_and_only_an_engineer_resumes(cell: tuple[Served, dict[str, str]],
                                                                 browser: Browser) -> None:
    served, tokens = cell
    page, errors = new_page(browser, served)
    log_in(page, tokens["operator"])
    page.click("#robot-stop")  # at once: the robot list may still be loading, and Stop must work then too
    expect(page.locator("#robot-status")).to_contain_text("stop sent")  # else it shows why Stop failed
    expect(page.locator("#rs-latched")).to_contain_text("latched by Stop")
    expect(page.locator("#robot-resume")).to_be_hidden()  # an operator may stop, not resume
    expect(page.locator("#robot-badge")).to_contain_text("STOPPED")  # the header shows the latch
    expect(page.locator("#header-resume")).to_be_hidden()
    page.screenshot(path=str(SHOTS / "operator-robot-latched.png"), full_page=True)
    page.close()
    page, errors2 = new_page(browser, served)
    log_in(page, tokens["engineer"])
    expect(page.locator("#robot-resume")).to_be_visible()
    page.click("#robot-resume")
    expect(page.locator("#robot-status")).to_contain_text("resumed")  # else it shows why resume failed
    expect(page.locator("#rs-latched")).to_have_text("no")
    expect(page.locator("#robot-resume")).to_be_hidden()
    with served.client(tokens["engineer"]) as http:
        assert http.get("/robots/robot0/motion").json()["latched"] is False
    assert errors == [] and errors2 == []
    page.close()
