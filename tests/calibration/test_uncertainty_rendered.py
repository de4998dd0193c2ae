"""Honest uncertainty on rendered sets: the truth lies within the reported projection uncertainty
for every target type and lens model, on images with the virtual camera's defects.

Small images and few views keep it fast; bench/intrinsics_rendered.py runs the same with more
seeds (median actual/reported over >= 10 seeds per target and model).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.intrinsics import calibrate, covered_points, projection_difference
from calibration.synthetic import plan_views
from calibration.targets import Charuco, Chessboard, CirclePlate
from drivers.sim.imaging import Imaging, PlanarObject, render

W, H = 400, 300
K = np.array([[350.0, 0.0, 201.5], [0.0, 349.0, 148.0], [0.0, 0.0, 1.0]])
TRUTHS = {
    "opencv5": np.array([-0.28, 0.09, 0.0008, -0.0006, -0.015]),
    "opencv8": np.array([0.15, -0.1, 0.0008, -0.0006, 0.01, 0.45, -0.05, 0.02]),
    "division": np.array([-0.3]),
}
TARGETS: dict[str, Chessboard | Charuco | CirclePlate] = {
    "chessboard": Chessboard(9, 6, 25.0), "charuco": Charuco(7, 5, 30.0, 22.0, "DICT_4X4_50"),
    "circle_plate": CirclePlate(7, 7, 15.0, 7.5)}
DEFECTS = Imaging(blur_sigma_px=0.7, gain_dn_per_e=0.5, read_noise_dn=1.5, vignetting=0.25, gamma=1.1,
                  jpeg_quality=92)
RATIOS: dict[tuple[str, str], float] = {}


@pytest.mark.parametrize("model", list(TRUTHS))
@pytest.mark.parametrize("target", list(TARGETS))
def test_truth_within_reported_uncertainty(target: str, model: str) -> None:
    truth = CameraModel(model, W, H, K, TRUTHS[model])  # type: ignore[arg-type]
    tgt = TARGETS[target]
    rng = np.random.default_rng(len(target) * 7 + len(model))
    poses = plan_views(truth, tgt, 8, rng, fill=0.6, margin_px=5, whole_outline=True)
    dets = [detect(render(truth, [PlanarObject(T, tgt.reflectance)], DEFECTS, rng), tgt, f"v{k}")
            for k, T in enumerate(poses)]
    found = [d for d in dets if d.found]
    assert len(found) >= 6, [d.reason for d in dets if not d.found]
    assert all(d.uv_sigma_px is not None for d in found)
    res = calibrate(found, tgt, model)
    reported = res.uncertainty["projection_rms_px"]
    actual = projection_difference(res.camera, truth, covered_points(res))["rms_px"]
    RATIOS[(target, model)] = actual / reported
    # one draw of an RMS over the covered cells: within 3 sigma, and not over-reported 10-fold
    assert actual < 3.0 * reported, (actual, reported)
    assert actual > 0.1 * reported, (actual, reported)


def test_median_ratio_over_all_sets_is_honest() -> None:
    """Across the target x model sets above (run in the same session), the median of
    actual / reported lies in [0.5, 2] (the issue's criterion)."""
    if len(RATIOS) < len(TARGETS) * len(TRUTHS):
        for target in TARGETS:
            for model in TRUTHS:
                if (target, model) not in RATIOS:
                    test_truth_within_reported_uncertainty(target, model)
    med = float(np.median(list(RATIOS.values())))
    assert 0.5 <= med <= 2.0, RATIOS
