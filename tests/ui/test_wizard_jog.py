"""The jog-to-mark wizard's jog buttons (engineer): each click moves the tool one step along a
base axis, the orientation kept, through the checked move API; an abandoned wizard's step times
out (routine side, see tests/cellctl/test_routine_params.py)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from playwright.sync_api import Browser, expect

from calibration import geometry as g
from tests.conftest import Served, start_served, stop_served
from tests.ui.conftest import SHOTS

expect.set_options(timeout=60_000)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("jog"))
    try:
        yield s
    finally:
        stop_served(s)


def _tool_mm(served: Served) -> np.ndarray:
    with served.client() as http:
        p = http.get("/robots/robot0/state").json()["pose_ur"]
    return np.array([p["x_m"], p["y_m"], p["z_m"], p["rx_rad"], p["ry_rad"], p["rz_rad"]]) * [1e3, 1e3, 1e3, 1, 1, 1]


def test_jog_buttons_move_the_tool_by_one_step(served: Served, browser: Browser) -> None:
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    page.goto(served.base_url + "/")
    page.fill("#token", served.token)
    page.click("#login-button")
    expect(page.locator("#who-role")).to_have_text("engineer")
    page.click("#tabs button[data-tab=wizard]")
    page.select_option("#wiz-marks", "4")
    page.click("#wiz-start-button")
    expect(page.locator("#wiz-record")).to_be_enabled()
    expect(page.locator("#wiz-jog")).to_be_visible()
    before = _tool_mm(served)
    page.select_option("#jog-step", "5")
    page.click("#wiz-jog button[data-axis='0'][data-sign='1']")
    expect(page.locator("#jog-status")).to_contain_text("tool at x")
    after_x = _tool_mm(served)
    page.select_option("#jog-step", "20")
    page.click("#wiz-jog button[data-axis='2'][data-sign='-1']")
    expect(page.locator("#jog-status")).to_contain_text(f"z {before[2] - 20:.1f}")
    after_z = _tool_mm(served)
    assert np.allclose(after_x[:3] - before[:3], [5.0, 0.0, 0.0], atol=0.1), after_x - before
    assert np.allclose(after_z[:3] - after_x[:3], [0.0, 0.0, -20.0], atol=0.1), after_z - after_x
    R0, R1 = g.rotvec_to_matrix(before[3:]), g.rotvec_to_matrix(after_z[3:])
    assert np.degrees(np.linalg.norm(g.matrix_to_rotvec(R0.T @ R1))) < 0.05  # orientation kept (repeatability)
    page.screenshot(path=str(SHOTS / "wizard-jog.png"), full_page=True)
    page.click("#wiz-cancel")
    expect(page.locator("#wiz-error")).to_contain_text("cancelled")
