"""The regularised solve (``calibrate(regularise=True)``, mrcal's rule, ``model.regularisation``): it holds
the rational model's coefficients near 0 where the data do not determine them, does not bias a
well-determined fit, and its (regularised) uncertainty stays honest."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.intrinsics import IntrinsicsError, calibrate, covered_point_means, projection_difference
from calibration.intrinsics.model import regularisation
from calibration.observations import Detection
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard

K = np.array([[1100.0, 0.0, 645.0], [0.0, 1098.0, 478.0], [0.0, 0.0, 1.0]])
RATIONAL = CameraModel("opencv8", 1280, 960, K, np.array([0.1, -0.05, 0.001, 0.0005, 0.002, 0.3, -0.02, 0.01]))
BOARD = Chessboard(9, 6, 30.0)
STEREO_RIGHT = Path(__file__).resolve().parents[1] / "data" / "opencv_stereo_9x6" / "right_corners.csv"


def _data(cam: CameraModel, seed: int, n_views: int, noise: float) -> list[Detection]:
    rng = np.random.default_rng(seed)
    return synthetic_detections(cam, BOARD, plan_views(cam, BOARD, n_views, rng), noise, rng)


def test_the_weights_follow_mrcals_rule() -> None:
    """mrcal 2.2's regularisation, measured through its optimizer_callback on 1080 measurements of an
    opencv8 640x480 camera: k1 = 1 gives a term of 0.2905 px, k4 = 1 (a denominator term) 1.4524 px,
    cx 10 px off centre 0.0232 px."""
    w, at = regularisation("opencv8", (640, 480), 1080)
    assert w[4] == pytest.approx(0.2905, abs=1e-4)
    assert w[4 + 5] == pytest.approx(1.4524, abs=1e-4)
    assert 10.0 * w[2] == pytest.approx(0.0232, abs=1e-4)
    assert np.all(w[:2] == 0.0) and at[2:4].tolist() == [319.5, 239.5]
    w5, _ = regularisation("opencv5", (640, 480), 1080)
    assert np.allclose(w5[4:], np.sqrt(1080 * 0.0025 / (5 * 4.0)))


def test_a_model_without_a_regularised_solve_is_refused_with_the_reason() -> None:
    with pytest.raises(IntrinsicsError, match="fisheye4 model has no regularised solve"):
        calibrate(_data(RATIONAL, 0, 6, 0.1), BOARD, "fisheye4", regularise=True)


def test_a_well_determined_fit_is_not_biased() -> None:
    """15 views of a lens with rational terms: the regularised camera is within 3 sigma of the truth
    and within a quarter of its own reported uncertainty of the unregularised one."""
    dets = _data(RATIONAL, 3, 15, 0.3)
    reg = calibrate(dets, BOARD, "opencv8", regularise=True)
    plain = calibrate(dets, BOARD, "opencv8")
    pts = covered_point_means(reg)
    unc = reg.uncertainty["projection_rms_px"]
    assert projection_difference(reg.camera, RATIONAL, pts)["rms_px"] < 3.0 * unc
    assert projection_difference(reg.camera, plain.camera, pts)["rms_px"] < 0.25 * unc
    # the prior adds information: the analytic (posterior) uncertainty is not larger than the plain one's
    # (up to the residual variance, which the prior's pull raises a little)
    assert reg.uncertainty["projection_rms_analytic_px"] <= 1.02 * plain.uncertainty["projection_rms_analytic_px"]


def test_the_rational_valley_is_held_on_a_real_set() -> None:
    """OpenCV's right stereo set (13 views, our corners): plain opencv8 wanders along the rational model's
    valley (|k4..k6| of several units or more), the regularised solve keeps them below 0.1, as mrcal's does,
    and fits the corners as well (RMS within 2 %)."""
    rows = np.genfromtxt(STEREO_RIGHT, delimiter=",", skip_header=1, dtype=None, encoding="utf-8")
    names = sorted({str(r[0]) for r in rows})
    dets = [Detection(n, True, ids=np.array([int(r[1]) for r in rows if r[0] == n]),
                      uv=np.array([[float(r[2]), float(r[3])] for r in rows if r[0] == n]), image_size=(640, 480))
            for n in names]
    board = Chessboard(9, 6, 1000.0)
    plain = calibrate(dets, board, "opencv8", jackknife=False)
    reg = calibrate(dets, board, "opencv8", jackknife=False, regularise=True)
    assert np.max(np.abs(plain.camera.dist[5:])) > 1.0, plain.camera.dist
    assert np.max(np.abs(reg.camera.dist[5:])) < 0.1, reg.camera.dist
    assert reg.rms_px < 1.02 * plain.rms_px


def test_regularised_uncertainty_is_honest_over_20_seeds() -> None:
    """Pooled actual / reported projection error (RMS over RMS, as test_uncertainty_honesty_seeds) within
    0.5-2 over 20 seeded sets of 8 views with independent 0.1 px noise, for a lens with rational terms (the
    prior's pull is a bias the covariance does not carry) and one without (the prior is right)."""
    for truth in (RATIONAL, CameraModel("opencv8", 1280, 960, K, np.array([-0.25, 0.08, 0.001, -0.0005, -0.01,
                                                                           0.0, 0.0, 0.0]))):
        act, rep = [], []
        for seed in range(2000, 2020):
            res = calibrate(_data(truth, seed, 8, 0.1), BOARD, "opencv8", regularise=True)
            act.append(projection_difference(res.camera, truth, covered_point_means(res))["rms_px"])
            rep.append(res.uncertainty["projection_rms_px"])
        ratio = float(np.sqrt(np.mean(np.square(act)) / np.mean(np.square(rep))))
        assert 0.5 <= ratio <= 2.0, (truth.dist.tolist(), ratio, np.round(np.divide(act, rep), 2).tolist())
