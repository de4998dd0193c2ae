"""The calibration report, from the CLI and the service, rendered in headless Chromium.

A camera calibration from real photographs (tests/data/udacity_camera_cal_9x6), a hand-eye and an
n-point calibration are stored in a real store, served by ``cellctl serve``; the CLI writes the
same camera's report with thumbnails. Chromium opens each report with every outside request
blocked and checks its plots (axes with ticks, colour bars, the valid-region contour, thumbnails,
the rejected views) and that no raw dump (Python lists, dicts, covariance, 16-digit floats) is
shown. Screenshots go to ``test-artifacts/screenshots/report-*.png``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page

from calibration.camera_model import CameraModel
from calibration.detect import detect_file
from calibration.handeye import RobotNoise, calibrate_handeye
from calibration.intrinsics import calibrate
from calibration.npoint import fit_npoint
from calibration.report import write_report
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard, target_from_dict
from cellctl.config import default_config_text
from cellctl.store import Store, sqlite_url
from tests.conftest import REPO, Served, start_served, stop_served
from tests.ui.conftest import SHOTS

IMAGES = REPO / "tests" / "data" / "udacity_camera_cal_9x6"
TARGET = {"type": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0}
RAW_DUMP = re.compile(r"\[\[|\{'|covariance|\d\.\d{7,}")


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("report")
    target = target_from_dict(TARGET, "test target")
    files = sorted(IMAGES.glob("*.jpg"))
    dets = [detect_file(f, target) for f in files]
    res = calibrate(dets, target, "opencv5")
    cli_report = tmp / "cli-report.html"
    write_report(res, cli_report, image_files=files)

    he_cam = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                         np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
    board, noise = Chessboard(8, 6, 30.0), RobotNoise(sigma_mm=0.05, sigma_deg=0.01)
    sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(3), camera=he_cam, target=board,
                           robot_noise=noise, pixel_sigma_px=0.05)
    he = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, he_cam, board, noise)

    rng = np.random.default_rng(7)
    uv = np.array([[u, v] for v in (200.0, 480.0, 760.0) for u in (300.0, 640.0, 980.0)])
    xy = np.column_stack([400 + 0.25 * uv[:, 0], 100 - 0.25 * uv[:, 1]]) + rng.normal(0, 0.05, (9, 2))
    npr = fit_npoint(uv, xy, "affine")
    pairs = [{"mark_id": k, "u_px": float(a), "v_px": float(b), "x_mm": float(x), "y_mm": float(y)}
             for k, ((a, b), (x, y)) in enumerate(zip(uv, xy, strict=True))]

    db = tmp / "store.db"
    with Store(sqlite_url(db), "virtual-cell") as store:
        ids = {
            "camera": store.save_calibration("camera", "cam0", None, res.to_json(),
                                             {"target": TARGET, "views": [d.to_json() for d in dets]}, "test").id,
            "handeye": store.save_calibration("handeye", "cam0", "robot0", he.to_json(), {}, "test").id,
            "npoint": store.save_calibration("npoint", "cam0", "robot0", npr.to_json(), {"pairs": pairs}, "test").id,
            "imported": store.save_calibration("camera", "cam1", None, res.to_json(), {}, "test", "imported").id,
        }
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    served = start_served(tmp, config=cfg)
    try:
        yield {"served": served, "ids": ids, "result": res, "cli_report": cli_report}
    finally:
        stop_served(served)


def _open(browser: Browser, url: str, token: str | None, local: str) -> tuple[Page, list[str], Any]:
    context = browser.new_context(viewport={"width": 1100, "height": 900},
                                  extra_http_headers={"Authorization": f"Bearer {token}"} if token else {})
    outside: list[str] = []

    def route(r: Any) -> None:
        if r.request.url.startswith(local) or r.request.url.startswith("data:"):
            r.continue_()
        else:
            outside.append(r.request.url)
            r.abort()

    context.route("**/*", route)
    page = context.new_page()
    page.goto(url)
    return page, outside, context


def _check_plots(page: Page, min_plots: int) -> None:
    plots = page.locator("svg.plot")
    assert plots.count() >= min_plots
    for k in range(plots.count()):
        svg = plots.nth(k)
        assert svg.locator("text.tick").count() >= 4, f"plot {k} has no tick labels"
        box = svg.bounding_box()
        assert box is not None and box["width"] > 200 and box["height"] > 150
    text = page.inner_text("body")
    assert not RAW_DUMP.search(text), RAW_DUMP.search(text)


def test_service_camera_report_in_chromium(cell: dict[str, Any], browser: Browser) -> None:
    s: Served = cell["served"]
    res = cell["result"]
    page, outside, context = _open(browser, f"{s.base_url}/calibrations/{cell['ids']['camera']}/report", s.token,
                                   s.base_url)
    try:
        _check_plots(page, 6)
        assert page.locator("svg.plot .colourbar").count() >= 1
        assert page.locator("svg.uncertainty text", has_text="limit").count() == 1
        assert page.locator("svg.coverage path.contour").count() == 1
        assert page.locator("svg.histogram").count() == 1
        rejected = [v for v in res.views if not v.used]
        assert rejected, "the test set has views of another size and without a board"
        table = page.locator("table.rejected")
        for v in rejected:
            assert table.locator("tr", has_text=v.image).count() == 1
        # Every used view, and each rejected one whose points were detected (another image size), has a thumbnail.
        for v in res.views:
            if v.used:
                assert page.locator("figure.thumb:not(.rejected)", has_text=v.image).count() == 1, v.image
        assert page.locator("figure.thumb.rejected").count() >= 1
        verdict = page.locator(".verdict").inner_text()
        assert ("NOT OK" in verdict) == (not res.verdict["ok"])
        page.screenshot(path=str(SHOTS / "report-camera-service.png"), full_page=True)
    finally:
        context.close()
    assert outside == []


def test_cli_report_is_the_service_report_with_photos(cell: dict[str, Any], browser: Browser) -> None:
    s: Served = cell["served"]
    served_html = httpx.get(f"{s.base_url}/calibrations/{cell['ids']['camera']}/report",  # built cold: seconds
                            headers={"Authorization": f"Bearer {s.token}"}, timeout=60).text
    cli_html = cell["cli_report"].read_text()
    for section in ("summary", "params", "rejected"):
        pattern = re.compile(f"<table class='{section}'>.*?</table>", re.S)
        a, b = pattern.search(cli_html), pattern.search(served_html)
        assert a is not None and b is not None and a.group(0) == b.group(0), section
    page, outside, context = _open(browser, cell["cli_report"].as_uri(), None, "file://")
    try:
        _check_plots(page, 6)
        thumbs = page.locator("figure.thumb image")
        assert thumbs.count() == sum(1 for v in cell["result"].views if len(v.uv))
        page.screenshot(path=str(SHOTS / "report-camera-cli.png"), full_page=True)
    finally:
        context.close()
    assert outside == []


def test_summary_agrees_with_the_plots(cell: dict[str, Any]) -> None:
    s: Served = cell["served"]
    with s.client() as http:
        data = http.get(f"/calibrations/{cell['ids']['camera']}/report", params={"format": "json"}).json()
        html = http.get(f"/calibrations/{cell['ids']['camera']}/report").text
    res = cell["result"]
    assert [v["rms_px"] for v in data["views"] if v["used"]] == pytest.approx(
        [v.rms_px for v in res.views if v.used], rel=1e-3)
    umap = np.array([[np.nan if x is None else x for x in row] for row in data["uncertainty_map_px"]])
    assert umap == pytest.approx(res.uncertainty_map_px, rel=1e-3, nan_ok=True)
    corners = [umap[0, 0], umap[0, -1], umap[-1, 0], umap[-1, -1]]
    from calibration.report.page import fmt

    assert f"<td class='num'>{fmt(max(corners))} px</td>" in html  # the summary's corner figure is the map's
    assert data["uncertainty_limit_px"] == 0.5


@pytest.mark.parametrize(("kind", "min_plots"), [("handeye", 3), ("npoint", 2)])
def test_handeye_and_npoint_reports_have_their_own_plots(cell: dict[str, Any], browser: Browser, kind: str,
                                                         min_plots: int) -> None:
    s: Served = cell["served"]
    page, outside, context = _open(browser, f"{s.base_url}/calibrations/{cell['ids'][kind]}/report", s.token,
                                   s.base_url)
    try:
        _check_plots(page, min_plots)
        if kind == "handeye":
            assert "held-out prediction" in page.inner_text("body")
            assert page.locator("table.matrix").count() == 2
        else:
            assert page.locator("svg.bubbles .bubble").count() >= 9  # the marks
            assert page.locator("svg.bubbles .legend use").count() >= 2  # and the scale legend
            assert "mm" in (page.locator("svg.bubbles").text_content() or "")
        page.screenshot(path=str(SHOTS / f"report-{kind}.png"), full_page=True)
    finally:
        context.close()
    assert outside == []


def test_a_camera_stored_without_detections_still_has_a_report(cell: dict[str, Any]) -> None:
    s: Served = cell["served"]
    with s.client() as http:
        r = http.get(f"/calibrations/{cell['ids']['imported']}/report")
        data = http.get(f"/calibrations/{cell['ids']['imported']}/report", params={"format": "json"}).json()
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "stored without its detections" in r.text
    assert r.text.count('<svg class="plot') == 2 and "class='params'" in r.text
    assert not RAW_DUMP.search(re.sub(r"<[^>]+>", " ", r.text))
    assert data["kind"] == "camera" and data["residual_px"]["n"] == 0


def test_the_page_opens_the_report_full_page_and_it_prints(cell: dict[str, Any], browser: Browser) -> None:
    """The Calibrations tab's report opens as a page of its own (Full page) and prints through its print
    stylesheet: A4, the page's width, no plot cut across two pages (emulated print media, a PDF from Chromium)."""
    from playwright.sync_api import expect

    s: Served = cell["served"]
    cal_id = cell["ids"]["camera"]
    context = browser.new_context(viewport={"width": 1300, "height": 900})
    try:
        page = context.new_page()
        page.goto(s.base_url + "/")
        page.fill("#token", s.token)
        page.click("#login-button")
        page.click("#tabs button[data-tab=calib]")
        page.locator(f"#calib-table tbody tr[data-id='{cal_id}'] button.report").click()
        expect(page.frame_locator("#report-frame").locator("h1")).to_contain_text(f"calibration {cal_id}",
                                                                                   timeout=90_000)
        with context.expect_page() as popup:
            page.click("#report-full")
        full = popup.value
        full.wait_for_load_state()
        expect(full.locator("h1")).to_contain_text(f"calibration {cal_id}")
        _check_plots(full, 6)
        screen_width = full.evaluate("getComputedStyle(document.body).maxWidth")
        full.emulate_media(media="print")
        printed = full.evaluate("""() => ({body: getComputedStyle(document.body).maxWidth,
            plot: getComputedStyle(document.querySelector('svg.plot')).breakInside,
            table: getComputedStyle(document.querySelector('table')).breakInside})""")
        assert screen_width == "980px" and printed == {"body": "none", "plot": "avoid", "table": "avoid"}, printed
        full.screenshot(path=str(SHOTS / "report-print-media.png"), full_page=True)
        pdf = full.pdf(prefer_css_page_size=True)
        pages = len(re.findall(rb"/Type\s*/Page[^s]", pdf))
        assert pdf.startswith(b"%PDF") and pages >= 2, pages
        assert re.search(rb"/MediaBox\s*\[\s*0\s+0\s+59[45]", pdf), "the PDF's pages are not A4"
        (SHOTS / "report-print.pdf").write_bytes(pdf)
    finally:
        context.close()
