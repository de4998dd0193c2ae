"""Honest uncertainty on rendered sets: the truth lies within the reported projection uncertainty
for every target type and lens model, on images with the virtual camera's defects.

Small images and few views keep it fast; bench/intrinsics_rendered.py runs the same with more
seeds (median actual/reported over >= 10 seeds per target and model).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.intrinsics import calibrate, covered_points, projection_difference
from calibration.observations import Detection
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


@dataclass(frozen=True)
class RenderedSet:
    """One target x model set: its detections (8 rendered views), the calibration and its check."""

    detections: list[Detection]
    reported_px: float
    """The calibration's reported projection RMS (pixels)."""
    actual_px: float
    """The projection difference to the true camera over the covered cells (RMS, pixels)."""

    @property
    def found(self) -> list[Detection]:
        return [d for d in self.detections if d.found]


@pytest.fixture(scope="module")
def rendered_sets() -> dict[tuple[str, str], RenderedSet]:
    """The sets this module has calibrated, by (target, model): each is rendered and calibrated once per
    process (deterministic: its own seed), and the median test reads those its parametrized tests made
    (module scope keeps the module on one xdist worker, docs/testing.md)."""
    return {}


def rendered_set(sets: dict[tuple[str, str], RenderedSet], target: str, model: str) -> RenderedSet:
    """The calibrated set of ``target`` x ``model`` (made once, then read from ``sets``)."""
    if (target, model) not in sets:
        truth = CameraModel(model, W, H, K, TRUTHS[model])  # type: ignore[arg-type]
        tgt = TARGETS[target]
        rng = np.random.default_rng(len(target) * 7 + len(model))
        poses = plan_views(truth, tgt, 8, rng, fill=0.6, margin_px=5, whole_outline=True)
        dets = [detect(render(truth, [PlanarObject(T, tgt.reflectance)], DEFECTS, rng), tgt, f"v{k}")
                for k, T in enumerate(poses)]
        found = [d for d in dets if d.found]
        assert len(found) >= 6, [d.reason for d in dets if not d.found]
        res = calibrate(found, tgt, model)
        actual = projection_difference(res.camera, truth, covered_points(res))["rms_px"]
        sets[(target, model)] = RenderedSet(dets, res.uncertainty["projection_rms_px"], actual)
    return sets[(target, model)]


@pytest.mark.parametrize("model", list(TRUTHS))
@pytest.mark.parametrize("target", list(TARGETS))
def test_truth_within_reported_uncertainty(target: str, model: str,
                                           rendered_sets: dict[tuple[str, str], RenderedSet]) -> None:
    got = rendered_set(rendered_sets, target, model)
    assert len(got.found) >= 6, [d.reason for d in got.detections if not d.found]
    assert all(d.uv_sigma_px is not None for d in got.found)
    actual, reported = got.actual_px, got.reported_px
    # one draw of an RMS over the covered cells: within 3 sigma, and not over-reported 10-fold
    assert actual < 3.0 * reported, (actual, reported)
    assert actual > 0.1 * reported, (actual, reported)


def test_median_ratio_over_all_sets_is_honest(rendered_sets: dict[tuple[str, str], RenderedSet]) -> None:
    """Across the target x model sets above, the median of actual / reported lies in [0.5, 2] (the
    issue's criterion); a set the parametrized tests have not made in this process is made here."""
    sets = {(target, model): rendered_set(rendered_sets, target, model) for target in TARGETS for model in TRUTHS}
    ratios = {key: got.actual_px / got.reported_px for key, got in sets.items()}
    med = float(np.median(list(ratios.values())))
    assert 0.5 <= med <= 2.0, ratios
