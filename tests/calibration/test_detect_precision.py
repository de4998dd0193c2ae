"""Each detected point carries its own precision (``Detection.uv_sigma_px``): it tracks the real
error as noise and blur change, survives the JSON round trip, and the solvers weight by it so
that a bad (noisy, blurred) view no longer dominates."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.intrinsics import calibrate, projection_difference
from calibration.observations import Detection, point_weights
from calibration.pose import estimate_pose
from calibration.synthetic import plan_views
from calibration.targets import Charuco, Chessboard, CirclePlate
from tests.calibration.conftest import plate_pose, render_target, truth_uv

BOARD = Chessboard(9, 6, 20.0)
PLATE = CirclePlate(7, 7, 12.5, 6.25)
CHARUCO = Charuco(7, 5, 20.0, 15.0, "DICT_4X4_50")


@pytest.mark.parametrize("target", [BOARD, PLATE, CHARUCO], ids=["chessboard", "circle_plate", "charuco"])
def test_sigma_grows_with_noise_and_blur_and_is_of_the_right_size(camera: CameraModel, target: object) -> None:
    T = plate_pose(target, 0.3 if target is not PLATE else 0.25, 25, tilt_dir_deg=30)  # type: ignore[arg-type]
    sig, err = [], []
    for noise, blur in ((1.0, 0.7), (6.0, 1.6)):
        img = render_target(camera, target, T, noise=noise, blur=blur, seed=3)  # type: ignore[arg-type]
        det = detect(img, target, "v.png")  # type: ignore[arg-type]
        assert det.found, det.reason
        assert det.uv_sigma_px is not None and det.uv_sigma_px.shape == (len(det.ids),)
        assert np.all(np.isfinite(det.uv_sigma_px)) and np.all(det.uv_sigma_px > 0)
        truth = truth_uv(camera, target, T)  # type: ignore[arg-type]
        idx = [list(target.points().ids).index(i) for i in det.ids]  # type: ignore[attr-defined]
        sig.append(float(np.median(det.uv_sigma_px)))
        err.append(float(np.sqrt(np.mean((det.uv - truth[idx]) ** 2))))
    assert sig[1] > 2.0 * sig[0]  # the noisy, blurred view says it is worse
    # at the high noise the random part dominates: the estimate is within 3x of the actual error
    assert err[1] / 3 < sig[1] < 3 * err[1], (sig, err)


def test_sigma_serialised_and_read_back() -> None:
    d = Detection("a.png", True, np.array([0, 1, 2]), np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]),
                  uv_sigma_px=np.array([0.01, 0.02, np.inf]), image_size=(640, 480))
    js = d.to_json()
    assert [p["sigma_px"] for p in js["points"]] == [0.01, 0.02, None]
    back = Detection.from_json(js)
    assert back.uv_sigma_px is not None
    assert back.uv_sigma_px[:2].tolist() == [0.01, 0.02] and np.isinf(back.uv_sigma_px[2])
    assert "sigma_px" not in Detection("b.png", True, np.array([0]), np.array([[1.0, 2.0]])).to_json()["points"][0]


def test_point_weights_follow_the_view_and_are_capped() -> None:
    w = point_weights([np.array([0.01, 0.01, 0.011]), np.array([0.04, 0.04, 0.04]), None,
                       np.array([0.0001, 0.0001]), np.array([0.01, 0.01, 0.2])], [3, 3, 2, 2, 3])
    assert np.allclose(w[0], 1.0, atol=0.01)  # the typical view weighs 1; small scatter inside a view is ignored
    assert np.all(w[1] < 0.3)                 # a 4x noisier view weighs far less
    assert np.allclose(w[2], 1.0)             # no uncertainties: weight 1
    assert np.all(w[3] < 2.3)                 # a view claiming 100x better precision is capped
    assert w[4][2] < 0.3 and np.allclose(w[4][:2], 1.0, atol=0.01)  # a point 20x its view is weighted down


def test_blurred_views_stop_dominating_intrinsics() -> None:
    """Half of the views are far noisier and say so; weighting by the stated precision brings the
    calibration closer to the truth than treating all points alike."""
    cam = CameraModel("opencv5", 1280, 960, np.array([[1100.0, 0, 645], [0, 1098, 478], [0, 0, 1]]),
                      np.array([-0.25, 0.08, 0.001, -0.0005, -0.01]))
    board = Chessboard(9, 6, 30.0)
    tp = board.points()
    errs_w: list[float] = []
    errs_u: list[float] = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        dets_w, dets_u = [], []
        for k, T in enumerate(plan_views(cam, board, 12, rng)):
            s = 0.03 if k % 2 else 0.4
            uv = cam.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, s, (len(tp.ids), 2))
            dets_w.append(Detection(f"v{k}", True, tp.ids.copy(), uv, image_size=cam.size,
                                    uv_sigma_px=np.full(len(tp.ids), s)))
            dets_u.append(Detection(f"v{k}", True, tp.ids.copy(), uv, image_size=cam.size))
        for dets, errs in ((dets_w, errs_w), (dets_u, errs_u)):
            res = calibrate(dets, board, "opencv5", jackknife=False)
            errs.append(projection_difference(res.camera, cam)["rms_px"])
    assert np.median(errs_w) < 0.7 * np.median(errs_u), (errs_w, errs_u)


def test_pose_weights_change_the_fit_not_the_reported_pixels(camera: CameraModel) -> None:
    T = plate_pose(BOARD, 0.3, 20)
    uv = truth_uv(camera, BOARD, T)
    rng = np.random.default_rng(0)
    bad = np.arange(len(uv)) < 10
    noisy = uv + rng.normal(0.0, 0.02, uv.shape) + np.where(bad[:, None], rng.normal(0.0, 2.0, uv.shape), 0.0)
    plain = estimate_pose(camera, BOARD.points().xyz_m, noisy)
    weighted = estimate_pose(camera, BOARD.points().xyz_m, noisy, np.where(bad, 0.01, 1.0))
    e_plain = np.linalg.norm(plain.T_cam_target[:3, 3] - T[:3, 3])
    e_w = np.linalg.norm(weighted.T_cam_target[:3, 3] - T[:3, 3])
    assert e_w < 0.5 * e_plain
    assert weighted.residuals_px.shape == uv.shape and weighted.rms_px > 0.5  # unweighted pixels
