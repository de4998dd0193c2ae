"""The page runs a production cell without curl (Chromium): the Recipes tab edits a production recipe
(search threshold, place section, gripper device), saves it as a new version, rolls it back,
duplicates and deletes one; the Pick form never defaults onto a stored recipe; the Production tab
shows the cycle table (filter, frame links, CSV download, parts/min) with no console error before a
run; the PLC tab (GET /plc/status, or a clear line without it) and the Audit tab (filters)."""

from __future__ import annotations

import csv
import io
import math
import re
import time
from pathlib import Path

import pytest
from playwright.sync_api import Browser, expect

from tests.support.production_cell import production_config, teach_recipe
from tests.support.served import start_served, stop_served
from tests.ui.conftest import SHOTS

WAIT_MS = 90_000
PLC_STATUS = {  # GET /plc/status as docs/rest.md documents it (the PLC front ends' status)
    "allow_motion": False, "insecure_plc_network": False, "busy": False, "running": None,
    "front_ends": {
        "modbus": {"enabled": True, "address": "127.0.0.1:5020", "host": "127.0.0.1", "port": 5020, "clients": 1,
                   "requests": 7, "refused_busy": 0, "last_request": {"command": "pick", "recipe": 1, "sequence": 7},
                   "last_answer": {"ok": True, "picks": 3, "latency_ms": 41.2}},
        "opcua": {"enabled": False, "address": "127.0.0.1:4840", "host": "127.0.0.1", "port": 4840, "clients": 0,
                  "requests": 0, "refused_busy": 0, "last_request": None, "last_answer": None},
    },
}


def test_recipes_production_plc_and_audit_from_the_page(tmp_path: Path, browser: Browser) -> None:
    served = start_served(tmp_path, production_config(tmp_path, count=4))
    http = served.client(timeout_s=60)
    try:
        teach_recipe(http)
        page = browser.new_page(viewport={"width": 1500, "height": 1200}, accept_downloads=True)
        page.set_default_timeout(WAIT_MS)
        errors: list[str] = []
        console: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
        failed: list[str] = []
        page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)
        page.goto(served.base_url + "/")
        page.fill("#token", served.token)
        page.click("#login-button")
        expect(page.locator("#who-role")).to_have_text("engineer")

        # Production before any run: "no run", and no 404 in the browser's console.
        page.click("#tabs button[data-tab=production]")
        expect(page.locator("#prod-state")).to_have_text("no run")
        time.sleep(2.5)  # a few polls
        assert console == [] and failed == [], (console, failed)

        # The Pick form proposes a new number, never recipe 1 that is stored.
        page.click("#tabs button[data-tab=pick]")
        expect(page.locator("#pick-recipes")).to_contain_text("1 bracket (v1)")
        expect(page.locator("#recipe-id")).to_have_value("2")

        # Recipes: open recipe 1, raise its search threshold, save as version 2.
        page.click("#tabs button[data-tab=recipes]")
        page.click("#recipes-table tbody tr[data-recipe='1']")
        expect(page.locator("#re-place-kind")).to_have_value("grid")
        expect(page.locator("#re-dev-io")).to_have_value("gripper0")
        expect(page.locator("#re-min-score")).to_have_value("0.7")
        v1 = http.get("/recipes/1").json()["data"]
        page.fill("#re-min-score", "0.75")
        page.fill("#re-dev-retries", "3")
        page.click("#re-save")
        expect(page.locator("#re-status")).to_contain_text("saved as version 2")
        expect(page.locator("#re-versions tbody tr")).to_have_count(2)
        v2 = http.get("/recipes/1").json()
        assert v2["version"] == 2 and v2["data"]["search"]["min_score"] == 0.75
        assert v2["data"]["gripper"]["device"]["retries"] == 3
        assert v2["data"]["place"] == v1["place"] and v2["data"]["models"] == v1["models"]  # kept as they were
        page.screenshot(path=str(SHOTS / "recipes-tab.png"), full_page=True)

        # A grasp moved off the part is refused with the reason (the fingers would close on nothing); nothing stored.
        expect(page.locator("#re-grasp-xy")).to_have_value("0,0")
        page.fill("#re-grasp-xy", "45,0")
        page.click("#re-save")
        expect(page.locator("#re-error")).to_contain_text("closes across no part material")
        assert http.get("/recipes/1").json()["version"] == 2
        page.fill("#re-grasp-xy", "0,0")

        # Roll back to version 1: stored as version 3 with version 1's data.
        page.locator("#re-versions tbody tr[data-version='1'] button").click()
        expect(page.locator("#re-status")).to_contain_text("version 1 is in force again, as version 3")
        expect(page.locator("#re-versions tbody tr")).to_have_count(3)
        assert http.get("/recipes/1").json()["data"] == v1

        # Duplicate as 5, then delete 5 (the page asks first).
        page.fill("#re-dup-id", "5")
        page.click("#re-dup")
        expect(page.locator("#recipes-table tbody tr[data-recipe='5']")).to_have_count(1)
        expect(page.locator("#re-title")).to_contain_text("5 ·")
        page.once("dialog", lambda d: d.accept())
        page.click("#re-delete")
        expect(page.locator("#recipes-table tbody tr[data-recipe='5']")).to_have_count(0)
        assert http.get("/recipes/5").status_code == 404

        # A run of 2 from the page; the recipe it uses cannot be deleted meanwhile.
        page.click("#tabs button[data-tab=production]")
        page.fill("#prod-recipe", "1")
        page.fill("#prod-count", "2")
        page.click("#prod-start")
        expect(page.locator("#prod-message")).to_have_text("run 1 started")  # the start has been answered
        refused = http.delete("/recipes/1")
        assert refused.status_code == 409 and refused.json()["error"]["code"] == "recipe_in_use", refused.text
        expect(page.locator("#prod-state")).to_have_text("complete", timeout=WAIT_MS)
        expect(page.locator("#cycles-table tbody tr")).to_have_count(2)
        rate = page.locator("#pc-rate").inner_text()
        assert re.fullmatch(r"\d+\.\d", rate) and float(rate) > 0, rate
        page.select_option("#cycles-filter", "placed")
        rows = page.locator("#cycles-table tbody tr")
        expect(rows).to_have_count(2)
        assert all(r == "placed" for r in page.locator("#cycles-table tbody tr td:nth-child(3)").all_inner_texts())
        page.select_option("#cycles-filter", "failed")
        expect(rows).to_have_count(0)
        page.select_option("#cycles-filter", "")
        expect(rows).to_have_count(2)
        page.locator("#cycles-table a.frame-link").first.click()
        expect(page.locator("#prod-frame")).to_have_attribute("data-url", re.compile(r"/cycles/1/frame\.png$"))
        with page.expect_download() as dl:
            page.click("#cycles-csv")
        table = list(csv.DictReader(io.StringIO(Path(dl.value.path()).read_text())))
        assert len(table) == 2 and all(r["result"] == "placed" for r in table)
        for row in table:  # whole poses: the tool points down, so the rotation vector is not all in rz
            rv = [float(row[f"place_{k}_rad"]) for k in ("rx", "ry", "rz")]
            assert math.hypot(*rv) == pytest.approx(math.pi, abs=0.2), rv
        page.screenshot(path=str(SHOTS / "production-cycles.png"), full_page=True)
        pose = http.get("/robots/robot0/state").json()["pose_ur"]
        assert [pose["x_m"], pose["y_m"], pose["z_m"]] == pytest.approx([0.45, -0.30, 0.25], abs=2e-3)  # home

        # PLC: the route's answer, or a clear line where the service has none; the table from its shape.
        page.click("#tabs button[data-tab=plc]")
        if http.get("/plc/status").status_code == 404:
            expect(page.locator("#plc-error")).to_contain_text("404")
        else:
            expect(page.locator("#plc-table tbody tr").first).to_be_visible()
        page.evaluate("async (s) => { const m = await import('/ui/plc.js'); m.showPlc(s); }", PLC_STATUS)
        expect(page.locator("#plc-table tbody tr")).to_have_count(2)
        modbus = page.locator("#plc-table tbody tr[data-front-end='modbus'] td").all_inner_texts()
        assert modbus[:6] == ["modbus", "yes", "127.0.0.1:5020", "1", "7", "0"] and "3 pick(s)" in modbus[7], modbus
        expect(page.locator("#plc-badge")).to_have_text("ready")
        page.screenshot(path=str(SHOTS / "plc-tab.png"), full_page=True)

        # Audit: filter by what, by robot, by who.
        page.click("#tabs button[data-tab=audit]")
        page.fill("#audit-what", "recipe.")
        page.click("#audit-refresh")
        expect(page.locator("#audit-count")).to_contain_text('what "recipe."')
        actions = page.locator("#audit-table tbody tr td:nth-child(3)").all_inner_texts()
        assert {"recipe.save", "recipe.activate", "recipe.duplicate", "recipe.delete"} <= set(actions), actions
        assert all(a.startswith("recipe.") for a in actions)
        page.fill("#audit-what", "")
        page.fill("#audit-robot", "robot0")
        page.fill("#audit-who", "session")
        page.click("#audit-refresh")
        expect(page.locator("#audit-count")).to_contain_text('robot "robot0", who "session", what ""')
        shown = page.locator("#audit-table tbody tr td:nth-child(3)").all_inner_texts()
        assert "robot.move" in shown and "recipe.save" not in shown, shown
        page.screenshot(path=str(SHOTS / "audit-tab.png"), full_page=True)
        assert errors == [], errors
        page.close()
    finally:
        http.close()
        stop_served(served)
