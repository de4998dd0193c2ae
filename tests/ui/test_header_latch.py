"""The page's header on a served virtual cell (Chromium): the Stop latch shows on every tab, Stop is
one click away on the Pick and Routines tabs where motion starts, Resume (engineer) beside it; the
Live tab's "Go to" sends the robot to a named pose of the config."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, Page, expect

from tests.support.served import Served, start_served, stop_served
from tests.ui.conftest import SHOTS

TABS = ("live", "calib", "wizard", "routines", "pick", "production")


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("latch"))
    try:
        yield s
    finally:
        stop_served(s)


@pytest.fixture()
def page(served: Served, browser: Browser) -> Iterator[Page]:
    p = browser.new_page(viewport={"width": 1440, "height": 1000})
    p.set_default_timeout(30_000)
    errors: list[str] = []
    p.on("pageerror", lambda e: errors.append(str(e)))
    p.goto(served.base_url + "/")
    p.fill("#token", served.token)
    p.click("#login-button")
    expect(p.locator("#who-role")).to_have_text("engineer")
    expect(p.locator("#robot-badge")).to_have_class("badge ok")
    yield p
    assert not errors, errors
    p.close()


def _stop_from(page: Page, tab: str) -> None:
    page.click(f"#tabs button[data-tab={tab}]")
    page.click("#header-stop")
    expect(page.locator("#robot-badge")).to_contain_text("STOPPED")


def _latch_shown_on_every_tab(page: Page) -> None:
    for tab in TABS:
        page.click(f"#tabs button[data-tab={tab}]")
        badge = page.locator("#robot-badge")
        expect(badge).to_be_visible()
        expect(badge).to_contain_text("robot0 STOPPED by session")
        expect(badge).to_contain_text("latched")
        expect(badge).to_have_class("badge bad latched")
        expect(page.locator("#header-stop")).to_be_visible()
        expect(page.locator("#header-resume")).to_be_visible()


def test_stop_from_pick_and_routines_shows_the_latch_on_every_tab(page: Page, served: Served) -> None:
    for start in ("pick", "routines"):
        _stop_from(page, start)
        _latch_shown_on_every_tab(page)
        if start == "pick":
            page.screenshot(path=str(SHOTS / "header-latched.png"), full_page=False)
        with served.client() as http:
            assert http.get("/robots/robot0/motion").json()["latched"] is True
        page.click("#tabs button[data-tab=routines]")
        page.click("#header-resume")
        expect(page.locator("#robot-badge")).to_have_class("badge ok", timeout=10_000)
        expect(page.locator("#robot-badge")).not_to_contain_text("STOPPED")
        expect(page.locator("#header-resume")).to_be_hidden()
        with served.client() as http:
            assert http.get("/robots/robot0/motion").json()["latched"] is False


def test_go_to_a_named_pose(page: Page, served: Served) -> None:
    page.click("#tabs button[data-tab=live]")
    expect(page.locator("#pose-select option")).to_have_count(2)
    page.select_option("#pose-select", "side")
    page.click("#pose-go")
    expect(page.locator("#pose-status")).to_have_text("at side", timeout=30_000)
    with served.client() as http:
        pose = http.get("/robots/robot0/state").json()["pose_ur"]
    assert abs(pose["x_m"] - 0.45) < 1e-4 and abs(pose["y_m"] - 0.1) < 1e-4
    expect(page.locator("#rs-y")).to_have_text(re.compile(r"^(99\.9\d|100\.0\d)$"), timeout=10_000)  # mm
    page.select_option("#pose-select", "home")
    page.click("#pose-go")
    expect(page.locator("#pose-status")).to_have_text("at home", timeout=30_000)
    # While latched, the move is refused and the page says why.
    page.click("#header-stop")
    expect(page.locator("#robot-badge")).to_contain_text("STOPPED")
    page.click("#pose-go")
    expect(page.locator("#pose-status")).to_contain_text("robot_stopped")
    page.click("#header-resume")
    expect(page.locator("#header-resume")).to_be_hidden()
