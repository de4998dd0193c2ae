"""The page's Production tab on a served production cell (Chromium): start a run, watch the counters
move to the end, see the last cycle's picture and the drift chart with its limits; the header's Stop
robot is there on every tab."""

from __future__ import annotations

import re
from pathlib import Path

from playwright.sync_api import Browser, expect

from tests.support.production_cell import production_config, teach_recipe
from tests.support.served import start_served, stop_served
from tests.ui.conftest import SHOTS

WAIT_MS = 90_000


def test_a_run_started_from_the_page_counts_up_to_the_end(tmp_path: Path, browser: Browser) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=3))
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http)
        for _ in range(21):  # the drift chart's baseline (20 checks) and one judged check
            assert http.post("/drift/check").status_code == 200
        page = browser.new_page(viewport={"width": 1440, "height": 1100})
        page.set_default_timeout(WAIT_MS)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(served.base_url + "/")
        page.fill("#token", served.token)
        page.click("#login-button")
        expect(page.locator("#who-role")).to_have_text("engineer")
        expect(page.locator("#header-stop")).to_be_visible()  # the emergency stop, whatever the tab
        page.click("#tabs button[data-tab=production]")
        expect(page.locator("#prod-state")).to_have_text("no run")
        page.fill("#prod-recipe", "1")
        page.fill("#prod-count", "2")
        page.click("#prod-start")
        # it counts while it runs (a poll may see 1, or the run already at 2)
        expect(page.locator("#pc-placed")).to_have_text(re.compile(r"^[12]$"), timeout=WAIT_MS)
        expect(page.locator("#prod-state")).to_have_text("complete", timeout=WAIT_MS)
        expect(page.locator("#pc-placed")).to_have_text("2")
        expect(page.locator("#pc-ended")).to_have_text("count_reached")
        expect(page.locator("#prod-frame")).to_be_visible()
        expect(page.locator("#pc-slot")).to_have_text("2")
        # the drift card: the state and the chart of the checks with its centre and limits (docs/drift.md)
        expect(page.locator("#drift-state")).to_have_text("ok")
        expect(page.locator("#drift-chart svg .drift-point")).to_have_count(21)
        expect(page.locator("#drift-chart svg .drift-ucl")).to_have_count(1)
        expect(page.locator("#drift-chart svg .drift-center")).to_have_count(1)
        expect(page.locator("#drift-limits")).to_contain_text("UCL")
        page.screenshot(path=str(SHOTS / "production-tab.png"), full_page=True)
        page.click("#tabs button[data-tab=live]")
        expect(page.locator("#header-stop")).to_be_visible()
        assert not errors, errors
        page.close()
    finally:
        stop_served(served)
