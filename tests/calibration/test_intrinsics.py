"""Intrinsics solver: truth recovered within the reported uncertainty, degenerate sets refused."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import circle_centre_bias_px
from calibration.intrinsics import IntrinsicsError, calibrate, covered_points, cross_validate, projection_difference
from calibration.observations import Detection
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard, CirclePlate, Points3D

K = np.array([[1100.0, 0.0, 645.0], [0.0, 1098.0, 478.0], [0.0, 0.0, 1.0]])
TRUTH = {
    "opencv5": CameraModel("opencv5", 1280, 960, K, np.array([-0.25, 0.08, 0.001, -0.0005, -0.01])),
    "opencv8": CameraModel("opencv8", 1280, 960, K,
                           np.array([0.1, -0.05, 0.001, 0.0005, 0.002, 0.3, -0.02, 0.01])),
    "division": CameraModel("division", 1280, 960, K, np.array([-0.2])),
}
BOARD = Chessboard(9, 6, 30.0)


def _data(model: str, seed: int, n_views: int = 15, noise: float = 0.3) -> list[Detection]:
    rng = np.random.default_rng(seed)
    cam = TRUTH[model]
    return synthetic_detections(cam, BOARD, plan_views(cam, BOARD, n_views, rng), noise, rng)


@pytest.mark.parametrize("model", ["opencv5", "opencv8", "division"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_truth_recovered_within_reported_uncertainty(model: str, seed: int) -> None:
    res = calibrate(_data(model, seed), BOARD, model)
    truth = TRUTH[model]
    assert res.rms_px == pytest.approx(0.3 * np.sqrt(2), rel=0.15)       # 0.3 px per axis noise
    err = projection_difference(res.camera, truth, covered_points(res))["rms_px"]
    unc = res.uncertainty["projection_rms_px"]
    assert 0.02 < unc < 1.0
    assert err < 3.0 * unc, (err, unc)
    sig = res.param_sigmas
    for i, name in enumerate(["fx", "fy", "cx", "cy"]):
        assert abs(res.camera.K.reshape(-1)[[0, 4, 2, 5][i]] - truth.K.reshape(-1)[[0, 4, 2, 5][i]]) \
            < 4.0 * sig[name] + 1e-9, name
    assert all(v.used for v in res.views)
    out = res.to_json()
    assert out["model"] == model and len(out["dist"]) == len(truth.dist)
    assert set(out["uncertainty"]["corners_px"]) == {"top_left", "top_right", "bottom_left", "bottom_right"}


def test_uncertainty_is_calibrated_over_seeds() -> None:
    """Across seeds the RMS of (actual error / reported uncertainty) is near 1 (0.5..2)."""
    ratios = []
    for seed in range(10, 16):
        res = calibrate(_data("opencv5", seed, n_views=12), BOARD, "opencv5")
        err = projection_difference(res.camera, TRUTH["opencv5"], covered_points(res))["rms_px"]
        ratios.append(err / res.uncertainty["projection_rms_px"])
    q = float(np.sqrt(np.mean(np.square(ratios))))
    assert 0.5 < q < 2.0, ratios


def test_noise_free_data_is_exact() -> None:
    res = calibrate(_data("division", 5, noise=0.0), BOARD, "division")
    assert res.rms_px < 1e-6
    assert res.camera.dist[0] == pytest.approx(-0.2, abs=1e-8)


def test_one_view_is_refused() -> None:
    with pytest.raises(IntrinsicsError, match="at least 3"):
        calibrate(_data("opencv5", 0)[:1], BOARD, "opencv5")


def test_all_views_parallel_are_flagged() -> None:
    """Frontal views moved around the image: focal length and distance cannot be separated."""
    cam = TRUTH["opencv5"]
    rng = np.random.default_rng(4)
    poses = []
    for dx, dy in [(-0.1, -0.05), (0.1, -0.05), (0.0, 0.0), (-0.1, 0.05), (0.1, 0.05), (0.05, 0.0)]:
        T = np.eye(4)
        T[:3, 3] = [dx - 0.12, dy - 0.075, 0.9]
        poses.append(T)
    dets = synthetic_detections(cam, BOARD, poses, 0.1, rng)
    try:
        res = calibrate(dets, BOARD, "opencv5")
    except IntrinsicsError as exc:
        assert "parallel" in str(exc) or "tilt" in str(exc)
        return
    codes = {p["code"] for p in res.verdict["problems"]}
    assert not res.verdict["ok"]
    assert "not_enough_tilt" in codes
    assert "focal_poorly_determined" in codes
    msg = next(p["message"] for p in res.verdict["problems"] if p["code"] == "not_enough_tilt")
    assert "horizontal axis" in msg and "vertical axis" in msg


def test_too_few_points_per_view_is_refused() -> None:
    dets = _data("opencv5", 0, n_views=5)
    for d in dets:
        d.ids, d.uv = d.ids[:4], d.uv[:4]
    with pytest.raises(IntrinsicsError, match="usable view"):
        calibrate(dets, BOARD, "opencv5")
    dets = _data("opencv5", 0, n_views=5)
    dets[0].ids, dets[0].uv = dets[0].ids[:4], dets[0].uv[:4]
    res = calibrate(dets, BOARD, "opencv5")
    assert not res.views[0].used and "only 4 points" in res.views[0].reason


def test_bad_inputs_have_clear_messages() -> None:
    dets = _data("opencv5", 0, n_views=4)
    with pytest.raises(IntrinsicsError, match="unknown model"):
        calibrate(dets, BOARD, "fisheye")
    with pytest.raises(IntrinsicsError, match="planar target"):
        calibrate(dets, Points3D({i: (float(i), float(i % 2), float(i % 3)) for i in range(6)}), "opencv5")
    dets[0].ids = dets[0].ids + 1000
    with pytest.raises(IntrinsicsError, match="do not exist on the target"):
        calibrate(dets, BOARD, "opencv5")


def test_few_views_and_uncovered_corners_in_verdict() -> None:
    dets = _data("opencv5", 3, n_views=5)
    res = calibrate(dets, BOARD, "opencv5")
    codes = {p["code"] for p in res.verdict["problems"]}
    assert "too_few_views" in codes
    assert not res.verdict["ok"]


def test_outlier_view_flagged_and_dropped() -> None:
    dets = _data("opencv5", 7, noise=0.2)
    rng = np.random.default_rng(0)
    dets[3].uv = dets[3].uv + rng.normal(0, 4.0, dets[3].uv.shape)
    res = calibrate(dets, BOARD, "opencv5")
    assert res.views[3].outlier
    assert res.verdict["advice"] and res.verdict["advice"][0]["code"] == "outlier_views"
    res2 = calibrate(dets, BOARD, "opencv5", drop_outliers=True)
    assert not res2.views[3].used and "outlier" in res2.views[3].reason
    assert res2.rms_px < 0.4 < res.rms_px


def test_circle_plate_bias_corrected_inside_the_loop() -> None:
    """Raw ellipse centres carry the perspective bias; the solver removes it with the current model."""
    cam = TRUTH["division"]
    plate = CirclePlate(7, 7, 25.0, 15.0)
    rng = np.random.default_rng(8)
    poses = plan_views(cam, plate, 12, rng, fill=0.5, max_tilt_deg=45)
    tp = plate.points()
    dets = []
    for k, T in enumerate(poses):
        centre = cam.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3])
        ell = centre + circle_centre_bias_px(cam, T, tp.xyz_m, plate.radius_m) + rng.normal(0, 0.02, centre.shape)
        dets.append(Detection(f"p{k}", True, tp.ids.copy(), ell.copy(), uv_ellipse=ell, image_size=cam.size))
    res = calibrate(dets, plate, "division")
    err = projection_difference(res.camera, cam, covered_points(res))["rms_px"]
    naive = [Detection(d.image, True, d.ids, d.uv, image_size=d.image_size) for d in dets]
    res_naive = calibrate(naive, plate, "division", jackknife=False)
    err_naive = projection_difference(res_naive.camera, cam, covered_points(res_naive))["rms_px"]
    assert res.rms_px < res_naive.rms_px
    assert err_naive > 5 * err
    assert err < 3 * res.uncertainty["projection_rms_px"]
    assert err < err_naive


def test_cross_validation_matches_uncertainty_for_the_right_model() -> None:
    dets = _data("division", 21, n_views=16)
    cv = cross_validate(dets, BOARD, "division", k=2)
    assert cv["k"] == 2 and len(cv["pairs"]) == 1
    assert cv["projection_difference_rms_px"] < 4 * cv["expected_from_uncertainty_px"]
    with pytest.raises(IntrinsicsError, match="too few"):
        cross_validate(dets[:5], BOARD, "division", k=2)


def test_projection_difference_compensates_rotation() -> None:
    cam = TRUTH["opencv5"]
    d = projection_difference(cam, cam)
    assert d["rms_px"] < 1e-6
    moved = CameraModel("opencv5", 1280, 960, K + np.array([[0, 0, 3.0], [0, 0, 0], [0, 0, 0]]), cam.dist)
    assert projection_difference(moved, cam, fit_rotation=False)["rms_px"] == pytest.approx(3.0, rel=0.05)
    assert projection_difference(moved, cam)["rms_px"] < 1.0
