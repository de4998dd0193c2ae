"""From the page alone: teach a part on the live picture, store it as a recipe, pick it (Chromium).

The served virtual cell has an active n-point map made from the cell's truth (pixels of the table
at the capture pose through the true camera onto the table plane), so the test judges the pick
against where the part really lies. The engineer takes a picture, drags the part's region with
the mouse, teaches (the model's edges are drawn), takes the capture pose from the robot, fills in
gripper settings, saves the recipe and picks with it; a recipe that searches an empty corner
answers no pick and says why. First, on the Live tab, the camera's exposure is set from the page.
Screenshots go to ``test-artifacts/screenshots/``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from calibration import geometry as g
from calibration.io import camera_from_json
from calibration.npoint import fit_npoint
from cellctl.cli import main
from cellctl.config import default_config_text
from cellctl.store import Store, sqlite_url
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.ui.conftest import SHOTS

WAIT_MS = 60_000
expect.set_options(timeout=WAIT_MS)


def _truth() -> dict[str, Any]:
    out = run_cellctl("sim", "truth", check=True).stdout
    return dict(json.loads(out))


def _truth_npoint(truth: dict[str, Any]) -> dict[str, Any]:
    """An n-point map from the truth: a grid of pixels through the true lens onto the table (z = 0)."""
    cam = camera_from_json(truth["camera"], "truth")
    T_base_cam = np.array(truth["T_base_cam"])
    uv = np.array([[u, v] for v in np.linspace(80, cam.height - 80, 5) for u in np.linspace(80, cam.width - 80, 5)])
    d = (T_base_cam[:3, :3] @ np.asarray(cam.unproject(uv), dtype=np.float64).T).T  # rays in the base frame
    o = T_base_cam[:3, 3]
    s = -o[2] / d[:, 2]
    xy_mm = (o[None, :2] + s[:, None] * d[:, :2]) * 1e3
    res = fit_npoint(uv, xy_mm, "homography", cam).to_json()
    res["capture_pose_ur"] = [float(v) for v in g.transform_to_ur_pose(np.array(truth["T_base_tool"]))]
    return res


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, dict[str, Any]]]:
    tmp = tmp_path_factory.mktemp("teach")
    truth = _truth()
    db = tmp / "store.db"
    with Store(sqlite_url(db), "virtual-cell") as store:
        rec = store.save_calibration("npoint", "cam0", "robot0", _truth_npoint(truth), {}, "test", "from truth")
        store.activate(rec.id, "test")
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    out = tmp / "engineer.json"
    assert main(["token", "add", "--config", str(cfg), "--name", "eng", "--role", "engineer", "--out", str(out)]) == 0
    served = start_served(tmp, config=cfg, token=json.loads(out.read_text())["token"])
    try:
        yield served, truth
    finally:
        stop_served(served)


def _drag_roi(page: Page, u0: float, v0: float, u1: float, v1: float) -> None:
    """Drag on the teach canvas from pixel (u0, v0) to (u1, v1) (pixel centres at +0.5 in canvas units)."""
    canvas = page.locator("#teach-canvas")
    box = canvas.bounding_box()
    assert box is not None
    w, h = canvas.evaluate("c => [c.width, c.height]")

    def client(u: float, v: float) -> tuple[float, float]:
        return box["x"] + (u + 0.5) * box["width"] / w, box["y"] + (v + 0.5) * box["height"] / h

    page.mouse.move(*client(u0, v0))
    page.mouse.down()
    for f in (0.3, 0.7, 1.0):
        page.mouse.move(*client(u0 + f * (u1 - u0), v0 + f * (v1 - v0)))
    page.mouse.up()


def test_teach_recipe_pick_from_the_page(cell: tuple[Served, dict[str, Any]], browser: Browser) -> None:
    served, truth = cell
    part = next(p for p in truth["parts"] if p["name"] == "bracket")
    cam = camera_from_json(truth["camera"], "truth")
    p_cam = g.transform_points(g.invert(np.array(truth["T_base_cam"])),
                               [part["x_mm"] * 1e-3, part["y_mm"] * 1e-3, part["z_mm"] * 1e-3])
    u, v = (float(x) for x in cam.project(p_cam)[0])

    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    page.set_default_timeout(WAIT_MS)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(served.base_url + "/")
    page.fill("#token", served.token)
    page.click("#login-button")
    expect(page.locator("#who-role")).to_have_text("engineer")
    # The Live tab's camera controls: the virtual camera's exposure, gain and trigger, set from the page.
    expect(page.locator("#cc-exposure")).to_have_value("10000")
    expect(page.locator("#cc-trigger")).to_have_value("software")
    page.fill("#cc-exposure", "8000")
    page.click("#cc-apply")
    expect(page.locator("#cc-status")).to_have_text("set exposure_us 8000")
    with served.client() as http:
        assert http.get("/cameras/cam0/settings").json()["exposure_us"] == 8000
    page.screenshot(path=str(SHOTS / "live-camera-controls.png"), full_page=True)
    page.fill("#cc-exposure", "10000")
    page.click("#cc-apply")
    expect(page.locator("#cc-status")).to_have_text("set exposure_us 10000")
    page.click("#tabs button[data-tab=pick]")
    expect(page.locator("#pick-recipes")).to_contain_text("no recipes stored yet")

    page.click("#teach-grab")
    expect(page.locator("#teach-canvas")).to_have_attribute("data-size", "1280x960")
    _drag_roi(page, u - 100, v - 100, u + 100, v + 100)
    roi = [float(x) for x in (page.locator("#teach-canvas").get_attribute("data-roi") or "").split(",")]
    assert np.allclose(roi, [u - 100, v - 100, 200, 200], atol=2.0), roi
    page.click("#teach-button")
    expect(page.locator("#teach-status")).to_contain_text("edge points")
    assert int(page.locator("#teach-canvas").get_attribute("data-edges") or 0) > 20
    page.screenshot(path=str(SHOTS / "teach-preview.png"), full_page=True)

    page.fill("#recipe-id", "9")
    page.fill("#recipe-name", "bracket")
    page.fill("#recipe-grasp-z", "5")
    page.fill("#grip-open", "40")
    page.fill("#grip-close", "18.5")
    page.click("#recipe-pose-button")
    expect(page.locator("#recipe-pose")).to_contain_text("x 400.0")
    # The grasp is drawn on the teach picture, at the reference point: the bracket's 18.5 mm lies from 5 to 24 mm
    # along the closing line (its reference point is off its material), so a finger opened 20 mm would come
    # down on it (what a save refuses for a parallel gripper device); centred on it (grasp y -14.5 mm in the
    # part's frame: the fingers close along the tool's y, the part's -y) it closes on the part's 18.5 mm.
    expect(page.locator("#teach-grasp")).to_contain_text("a finger would come down on the part")
    fingers = [float(x) for x in (page.locator("#teach-canvas").get_attribute("data-grasp") or "").split(",")]
    centre = ((fingers[0] + fingers[2]) / 2, (fingers[1] + fingers[3]) / 2)
    assert np.hypot(centre[0] - (roi[0] + roi[2] / 2), centre[1] - (roi[1] + roi[3] / 2)) < 1.0, (centre, roi)
    page.fill("#grasp-y", "-14.5")
    expect(page.locator("#teach-grasp")).to_contain_text("the fingers open 40.0 mm and close on 18.")
    page.screenshot(path=str(SHOTS / "teach-grasp.png"), full_page=True)
    page.fill("#grasp-y", "0")
    page.fill("#grasp-x", "150")
    expect(page.locator("#teach-grasp")).to_contain_text("closes across no part material")
    moved = [float(x) for x in (page.locator("#teach-canvas").get_attribute("data-grasp") or "").split(",")]
    assert np.hypot((moved[0] + moved[2]) / 2 - centre[0], (moved[1] + moved[3]) / 2 - centre[1]) > 50, moved
    page.screenshot(path=str(SHOTS / "teach-grasp-off-part.png"), full_page=True)
    page.fill("#grasp-x", "0")
    expect(page.locator("#teach-grasp")).to_contain_text("a finger would come down on the part")
    page.click("#recipe-save")
    expect(page.locator("#recipe-status")).to_contain_text("recipe 9")
    expect(page.locator("#recipe-status")).to_contain_text("with its capture pose")
    expect(page.locator("#pick-recipes")).to_contain_text("9 bracket (v1)")

    with served.client() as http:
        stored = http.get("/recipes/9").json()
    data = stored.get("data", stored)
    assert np.allclose(data["capture_pose_ur"], [0.40, 0.0, 0.55, np.pi, 0.0, 0.0], atol=1e-3)
    assert data["gripper"]["open_width_mm"] == 40 and data["gripper"]["grip_width_mm"] == 18.5
    assert data["models"][0]["teach"]["roi"] == pytest.approx(roi, abs=0.1)
    assert data["grasp_offset_mm"] == [0, 0] and data["grasp_yaw_deg"] == 0

    page.click("#pick-button")
    expect(page.locator("#pick-table")).to_be_visible()
    expect(page.locator("#pick-image")).to_be_visible()
    first = page.locator("#pick-table tbody tr").first.locator("td").all_inner_texts()
    assert first[1] == "bracket" and first[-1] == "yes", first
    with served.client() as http:  # the pick frame the page shows has the grasp drawn on it (blue fingers)
        shown = http.post("/pick", json={"recipe_id": 9}).json()
        g0 = shown["picks"][0]["grasp_px"]
        png = http.get(shown["image_url"]).content
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    fu, fv = (int(round(x)) for x in g0["fingers_px"][0])
    patch = img[fv - 2:fv + 3, fu - 2:fu + 3].reshape(-1, 3).astype(int)
    assert ((patch[:, 0] > 200) & (patch[:, 2] < 60)).any(), patch  # the finger's blue (BGR 255, 120, 0)
    x_mm, y_mm = float(first[5]), float(first[6])
    assert np.hypot(x_mm - part["x_mm"], y_mm - part["y_mm"]) < 1.5, (x_mm, y_mm)
    assert page.locator("#pick-reason").inner_text() == ""
    page.screenshot(path=str(SHOTS / "teach-pick.png"), full_page=True)

    # A recipe searching an empty corner finds nothing and says why (REST and page).
    with served.client() as http:
        empty = {**data, "search": {**data.get("search", {}), "roi": [0, 0, 120, 120]}}
        assert http.post("/recipes", json={"recipe_id": 10, "recipe": empty}).status_code == 201
        answer = http.post("/pick", json={"recipe_id": 10}).json()
    assert answer["picks"] == [] and ("searched region" in answer["reason"] or "min_score" in answer["reason"])
    page.click("#tabs button[data-tab=live]")
    page.click("#tabs button[data-tab=pick]")
    expect(page.locator("#pick-recipe option[value='10']")).to_have_count(1)
    page.select_option("#pick-recipe", "10")
    page.click("#pick-button")
    expect(page.locator("#pick-reason")).to_have_text(answer["reason"])
    assert errors == []
