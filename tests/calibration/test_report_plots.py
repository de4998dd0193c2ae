"""The report's figures (matplotlib, inline SVG): a good and a bad calibration look different, views
and stations are named on their axis, residuals against the radius, hand-eye residuals per station
in mm and degrees equal to the result's, and the capture's rejected count as the job reported it."""

from __future__ import annotations

import base64
import re
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.handeye import RobotNoise, calibrate_handeye, calibrate_handeye_dof4, calibrate_handeye_measured
from calibration.intrinsics import calibrate
from calibration.report import calibration_report, report_json
from calibration.report import camera as rc
from calibration.report.camera_plots import RADIUS_BINS, RESIDUAL_BAND, radius_figure, thumbnails, view_bars
from calibration.report.html import camera_summary
from calibration.report.plots import Band, short_name
from calibration.synthetic import perturb_pose, plan_views, simulate_handeye, simulate_scara, synthetic_detections
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1280, 960, np.array([[1100.0, 0, 641], [0, 1100.0, 479], [0, 0, 1]]),
                  np.array([-0.15, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(9, 6, 25.0)
TARGET = {"type": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0}


def _svg(html: str, css: str) -> ET.Element:
    """The first ``<svg class="plot css">`` of ``html``, parsed."""
    found = re.search(rf'<svg class="plot {css}".*?</svg>', html, re.S)
    assert found is not None, f"no {css} plot"
    return ET.fromstring(found.group(0))


def _fill(el: ET.Element) -> str:
    """The fill colour of a tagged bar (its path's style)."""
    path = el.find("{*}path")
    assert path is not None
    m = re.search(r"fill: (#[0-9a-f]{6})", path.get("style", ""))
    assert m is not None, path.get("style")
    return m.group(1)


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    return int(hex_colour[1:3], 16), int(hex_colour[3:5], 16), int(hex_colour[5:7], 16)


def _calibration(noise_px: float, n_views: int = 8) -> tuple[dict[str, Any], dict[str, Any]]:
    """A camera calibration of ``n_views`` planned views (the same views whatever the noise): its result
    and stored inputs."""
    rng = np.random.default_rng(5)
    dets = synthetic_detections(CAM, BOARD, plan_views(CAM, BOARD, n_views, rng), noise_px, rng)
    return calibrate(dets, BOARD, "opencv5").to_json(), {"target": TARGET, "views": [d.to_json() for d in dets]}


def test_a_good_and_a_bad_calibration_look_different_and_name_their_views() -> None:
    good, good_in = _calibration(0.05)
    bad, bad_in = _calibration(1.6)
    good_html = view_bars(rc.build(good, good_in["views"], BOARD))
    bad_html = view_bars(rc.build(bad, bad_in["views"], BOARD))
    bars = {}
    for name, html in (("good", good_html), ("bad", bad_html)):
        svg = _svg(html, "views")
        bars[name] = {b.get("data-name"): b for b in svg.iterfind(".//{*}g[@class='bar view']")}
        ticks = [t.text for t in svg.iterfind(".//{*}text[@class='tick']")]
        assert [f"view{k:02d}" for k in range(8)] == [n for n in ticks if n and n.startswith("view")]
    assert set(bars["good"]) == set(bars["bad"]) == {f"view{k:02d}" for k in range(8)}
    good_rms = {v["image"]: v["rms_px"] for v in good["views"]}
    bad_rms = {v["image"]: v["rms_px"] for v in bad["views"]}
    for view in bars["good"]:
        g, b = bars["good"][view], bars["bad"][view]
        assert float(g.get("data-value", "nan")) == pytest.approx(good_rms[view], rel=1e-5)
        assert float(b.get("data-value", "nan")) == pytest.approx(bad_rms[view], rel=1e-5)
        assert good_rms[view] < RESIDUAL_BAND.good < RESIDUAL_BAND.bad < bad_rms[view]
        (r1, g1, _), (r2, g2, _) = _rgb(_fill(g)), _rgb(_fill(b))
        assert g1 > r1 and r2 > g2, (view, _fill(g), _fill(b))  # green against red, for the same view


def test_band_is_anchored_to_its_limits_and_fitted_to_the_data() -> None:
    band = Band(0.3, 1.0, "px")
    small, large = np.array([0.02, 0.05, 0.08]), np.array([0.5, 2.0, 4.0])
    # Anchored: the hue follows the limits whatever else is shown.
    for value, data in ((0.05, small), (0.05, large), (0.25, small)):
        r, g, _ = band.rgb([value], data)[0]
        assert g > r, (value, data)
    for value, data in ((1.5, small), (1.5, large), (4.0, large)):
        r, g, _ = band.rgb([value], data)[0]
        assert r > 2 * g, (value, data)
    # Fitted: good values differ in shade over the data shown; beyond the data's top, red saturates.
    shades = band.rgb(small, small)
    assert np.ptp(shades[:, 1]) > 0.2
    assert band.top(small) == 1.0 and band.top(large) == 4.0
    assert np.allclose(band.rgb([4.0], large), band.rgb([40.0], large))
    assert np.all(band.rgb([np.nan], small) == 0.75)
    with pytest.raises(ValueError, match="good < bad"):
        Band(1.0, 0.5, "px")


def test_residuals_against_the_radius_are_the_binned_data() -> None:
    """Residuals growing with the radius (a lens model that does not fit) show as a rising curve, each
    bin's plotted RMS the RMS of the points at that radius."""
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [1279, 959], (600, 2))
    centre = np.array([CAM.K[0, 2], CAM.K[1, 2]])
    radius = np.linalg.norm(uv - centre, axis=1)
    resid = (uv - centre) * 1e-3  # 1 px per 1000 px of radius, pointing outward
    view = rc.ViewData("view00", True, 0.4, uv=uv, residuals_px=resid)
    rep = rc.CameraReport(CAM, {"rms_px": 0.4}, [view], np.ones((12, 16), dtype=np.int64), np.zeros((12, 16)))
    svg = ET.fromstring(radius_figure(rep))
    assert svg.get("class") == "plot radius"
    line = svg.find(".//{*}g[@class='radius-rms']")
    assert line is not None
    plotted = np.array([float(x) for x in line.get("data-values", "").split()])
    assert len(plotted) == RADIUS_BINS and np.all(np.diff(plotted[np.isfinite(plotted)]) > 0)
    edges = np.linspace(0.0, float(np.hypot(641, 480)), RADIUS_BINS + 1)
    inner = radius < edges[1]
    assert plotted[0] == pytest.approx(np.sqrt(np.mean(np.sum(resid[inner] ** 2, axis=1))), rel=1e-3)
    assert svg.find(".//{*}g[@class='radius-points']").get("data-n") == "600"  # type: ignore[union-attr]
    assert "distance from the principal point (px)" in ET.tostring(svg, encoding="unicode")


def _station_bars(html: str, css: str, unit: str) -> dict[str, float]:
    svg = _svg(html, css)
    return {b.get("data-name", ""): float(b.get("data-value", "nan"))
            for b in svg.iterfind(f".//{{*}}g[@class='bar {unit}']")}


def test_handeye_stations_in_mm_and_degrees_are_the_result() -> None:
    cam = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                      np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
    board, noise = Chessboard(8, 6, 30.0), RobotNoise(sigma_mm=0.05, sigma_deg=0.01)
    sim = simulate_handeye("eye-in-hand", 8, np.random.default_rng(3), camera=cam, target=board,
                           robot_noise=noise, pixel_sigma_px=0.05)
    res = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, cam, board, noise).to_json()
    html = calibration_report("handeye", res)
    poses = {str(p["image"]): p for p in res["poses"]}
    assert len(poses) == 8
    for css, unit, key in (("heldout", "mm", "loo_mm"), ("heldout", "deg", "loo_deg"),
                           ("corrections", "mm", "robot_correction_mm"),
                           ("corrections", "deg", "robot_correction_deg")):
        plotted = _station_bars(html, css, unit)
        assert set(plotted) == set(poses), (css, unit)
        for name, value in plotted.items():
            assert value == pytest.approx(poses[name][key], rel=1e-5, abs=1e-12), (css, unit, name)
    ticks = [t.text for t in _svg(html, "heldout").iterfind(".//{*}text[@class='tick']")]
    assert all(short_name(n) in ticks for n in poses)  # the stations are named on the axis
    table = re.search(r"<table class='stations'>.*?</table>", html, re.S)
    assert table is not None and all(n in table.group(0) for n in poses)
    assert "held-out position error (mm)" in html and "held-out rotation error (deg)" in html


def test_dof4_stations_come_from_its_leave_one_out() -> None:
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                      np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
    s = simulate_scara("eye-in-hand", 8, np.random.default_rng(2), camera=cam, target=Chessboard(7, 5, 25.0),
                       robot_noise=RobotNoise(0.02, 0.01))
    res = calibrate_handeye_dof4("eye-in-hand", s.G_recorded, s.detections, cam, s.target, s.target_z_mm,
                                 RobotNoise(0.02, 0.01)).to_json()
    html = calibration_report("handeye", res)
    per_pose = res["leave_one_out"]["per_pose"]
    mm, deg = _station_bars(html, "heldout", "mm"), _station_bars(html, "heldout", "deg")
    assert [mm[str(p["image"])] for p in per_pose] == pytest.approx([p["position_mm"] for p in per_pose], rel=1e-5)
    assert [deg[str(p["image"])] for p in per_pose] == pytest.approx([p["rotation_deg"] for p in per_pose],
                                                                     rel=1e-5)
    figures = report_json("handeye", res)  # the JSON carries the same per-station figures
    assert figures["dof"] == 4 and figures["leave_one_out"]["per_pose"] == per_pose


def test_a_measured_frame_shows_each_stations_own_solution() -> None:
    """A measured target frame has no held-out solve: each station's own solution against the joint one."""
    noise = RobotNoise(0.03, 0.005)
    rng = np.random.default_rng(9)
    s = simulate_handeye("eye-in-hand", 4, rng, camera=CAM, target=BOARD, robot_noise=noise)
    res = calibrate_handeye_measured("eye-in-hand", s.G_recorded, s.detections, CAM, BOARD,
                                     perturb_pose(s.Z_true, rng, noise), noise, noise).to_json()
    html = calibration_report("handeye", res)
    mm, deg = _station_bars(html, "heldout", "mm"), _station_bars(html, "heldout", "deg")
    assert [mm[str(p["image"])] for p in res["poses"]] == pytest.approx(
        [p["single_station_diff_mm"] for p in res["poses"]], rel=1e-5)
    assert [deg[str(p["image"])] for p in res["poses"]] == pytest.approx(
        [p["single_station_diff_deg"] for p in res["poses"]], rel=1e-5)
    assert "position difference (mm)" in html and "plot corrections" not in html  # no robot correction here


def test_a_thumbnail_keeps_its_jpeg_upright_under_the_residuals() -> None:
    """The page keeps the small JPEG it was given (not a re-encoded PNG), drawn upright over the view's box."""
    import cv2

    photo = np.zeros((480, 640), np.uint8)
    photo[240:] = 255  # dark above, bright below: upside down would swap them
    jpeg = bytes(cv2.imencode(".jpg", photo)[1])
    cam = CameraModel("opencv5", 640, 480, np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]]), np.zeros(5))
    uv = np.array([[100.0, 100.0], [500.0, 400.0]])
    view = rc.ViewData("v.jpg", True, 0.2, uv=uv, residuals_px=np.full((2, 2), 0.1), thumbnail=jpeg)
    rep = rc.CameraReport(cam, {}, [view], np.ones((12, 16), dtype=np.int64), np.zeros((12, 16)))
    figure = re.search(r"<svg class=\"thumb\".*?</svg>", thumbnails(rep), re.S)
    assert figure is not None
    svg = ET.fromstring(figure.group(0))
    image = svg.find(".//{*}image")
    assert image is not None and image.get("class") == "photo" and "transform" not in image.attrib
    href = image.get("{http://www.w3.org/1999/xlink}href", "")
    assert href == "data:image/jpeg;base64," + base64.b64encode(jpeg).decode()
    box = [float(image.get(k, "nan")) for k in ("x", "y", "width", "height")]
    assert box == pytest.approx([0.0, 0.0, float(svg.get("width", "0")), float(svg.get("height", "0"))], abs=1.0)


def test_the_capture_rejections_are_the_jobs() -> None:
    """The job's ``views_rejected`` counts the shots the capture dropped before calibrating; the report
    shows the same number beside the solver's own rejections."""
    res, views = _calibration(0.05, 10)
    res["verdict"]["coverage_missing"] = {"corners": [], "views_tried": 14, "budget": 32}  # a planned capture's
    summary = camera_summary(rc.build(res, views["views"], BOARD, inputs=views))
    assert "<th>views tried by the capture / rejected there (not calibrated)</th><td class='num'>14 / 4</td>" in summary
    assert report_json("camera", res, views)["capture"] == {"views_tried": 14, "views_rejected": 4}
    kept = {**views, "capture": {"views_tried": 13, "views_rejected": 3}}  # what the routine stored wins
    assert report_json("camera", res, kept)["capture"] == {"views_tried": 13, "views_rejected": 3}
    del res["verdict"]["coverage_missing"]
    assert "views tried by the capture" not in camera_summary(rc.build(res, views["views"], BOARD, inputs=views))
    assert "capture" not in report_json("camera", res, views)
