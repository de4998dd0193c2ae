"""4-DOF hand-eye says when its stations limit the mapping: the calibration's own part of the map error
it predicts is what a held-out set measures against the true calibration, it warns when mapped points
would be worse than 1.2x the truth's, and the station count it asks for meets that on held-out data."""

from __future__ import annotations

import numpy as np

from calibration.camera_model import CameraModel
from calibration.handeye import RobotNoise, calibrate_handeye_dof4
from calibration.measure import map_handeye
from calibration.synthetic import simulate_scara
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 25.0)
NOISE = RobotNoise(0.02, 0.01)


def _heldout(n: int, seed: int) -> tuple[dict, float, float, float]:
    """Eye-to-hand: solve on n stations; on a held-out set, RMS map error (mm) of the solution, of the
    true calibration, and of solution vs truth on the same pixels."""
    s = simulate_scara("eye-to-hand", n, np.random.default_rng(seed), camera=CAM, target=BOARD, robot_noise=NOISE)
    ho = simulate_scara("eye-to-hand", 6, np.random.default_rng([seed, 26]), camera=CAM, target=BOARD,
                        robot_noise=NOISE)
    he = calibrate_handeye_dof4("eye-to-hand", s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm, NOISE,
                                leave_one_out=False).to_json()
    truth = {**he, "T_base_cam": s.X_true.tolist()}
    e, t, d = [], [], []
    for det, P in zip(ho.detections, ho.points_base_true, strict=True):
        for j in range(0, len(P), 3):
            a = map_handeye(he, det.uv[j], CAM, P[j, 2] * 1e3, None, with_uncertainty=False).xyz_mm[:2]
            b = map_handeye(truth, det.uv[j], CAM, P[j, 2] * 1e3, None, with_uncertainty=False).xyz_mm[:2]
            e.append(np.linalg.norm(a - P[j, :2] * 1e3))
            t.append(np.linalg.norm(b - P[j, :2] * 1e3))
            d.append(np.linalg.norm(a - b))
    rms = [float(np.sqrt(np.mean(np.square(v)))) for v in (e, t, d)]
    return he, rms[0], rms[1], rms[2]


def test_predicted_part_matches_held_out_and_warns() -> None:
    """14 eye-to-hand stations: the solver's predicted calibration part (mm) is the held-out one (RMS over
    seeds), the predicted ratio is over 1.2x and the result warns with the stations to add."""
    pred, got, pix, pix_pred = [], [], [], []
    for seed in range(300, 306):
        he, _, t, d = _heldout(14, seed)
        b = he["mapping_budget"]
        pred.append(b["calibration_part_mm"])
        pix_pred.append(b["true_calibration_map_mm"])
        got.append(d)
        pix.append(t)
        w = [p for p in he["verdict"]["problems"] if p["code"] == "stations_limit_mapping"]
        if b["predicted_ratio_to_true_calibration"] > 1.2:
            assert w and f"capture {b['stations_for_ratio_target']} stations" in w[0]["message"], w
            assert b["stations_for_ratio_target"] > 14
        else:
            assert not w
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    assert 0.6 < rms(got) / rms(pred) < 1.5, (got, pred)
    assert 0.85 < rms(pix) / rms(pix_pred) < 1.15, (pix, pix_pred)
    assert np.median([p / q for p, q in zip(pred, pix_pred, strict=True)]) > 0.66  # i.e. predicted ratio > 1.2


def test_the_stations_it_asks_for_meet_the_ratio() -> None:
    """With the station count the 14-station result asks for (1.5x in 19 of 20 captures), the held-out
    ratio's median is <= 1.2x and at most one of 6 seeds is over 1.5x; at 14 stations the median is over 1.15."""
    he, *_ = _heldout(14, 300)
    b = he["mapping_budget"]
    n = b["stations_for_1.5x_in_19_of_20"]
    assert b["stations_for_ratio_target"] < n <= 40
    ratios = []
    for seed in range(310, 316):
        he_n, e, t, _ = _heldout(n, seed)
        assert he_n["mapping_budget"]["stations"] == n
        ratios.append(e / t)
    assert np.median(ratios) <= 1.2 and sum(r > 1.5 for r in ratios) <= 1, ratios
