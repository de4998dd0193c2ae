"""The N-point verdict: ok on good jog-to-mark data; each rule fails (or advises) on its case."""

from __future__ import annotations

import numpy as np

from calibration.camera_model import CameraModel
from calibration.npoint import MAX_LOO_RMS_MM, assess_npoint, fit_npoint
from calibration.synthetic import simulate_npoint

SIZE = (1920, 1200)


def _cam() -> CameraModel:
    return CameraModel("opencv5", *SIZE, np.array([[1900.0, 0, 960], [0, 1900.0, 600], [0, 0, 1]]), np.zeros(5))


def _codes(v: dict) -> list[str]:
    return [p["code"] for p in v["problems"]]


def test_good_marks_are_ok_and_figures_are_reported() -> None:
    for seed in range(3):
        uv, xy, _ = simulate_npoint(np.random.default_rng(seed), _cam())
        v = assess_npoint(fit_npoint(uv, xy), uv, xy, SIZE)
        assert v["ok"] is True, v
        assert v["marks"] == 9 and 0 < v["loo_rms_mm"] < MAX_LOO_RMS_MM
        assert len(v["loo_mm"]) == 9 and 0.1 < v["hull_fraction"] < 0.3 and v["hull_aspect"] > 0.5


def test_a_mis_recorded_mark_fails_and_is_named() -> None:
    uv, xy, _ = simulate_npoint(np.random.default_rng(4), _cam())
    xy = xy.copy()
    xy[6] += [1.5, -1.0]  # the operator pressed record 1.8 mm off mark 7
    v = assess_npoint(fit_npoint(uv, xy, "homography"), uv, xy, SIZE)
    assert v["ok"] is False and "loo_too_large" in _codes(v)
    msg = next(p["message"] for p in v["problems"] if p["code"] == "loo_too_large")
    assert "worst: mark 7" in msg and "re-record" in msg
    assert any(a["code"] == "outlier_mark" and "mark 7" in a["message"] for a in v["advice"])


def test_too_few_marks_for_the_model() -> None:
    uv, xy, _ = simulate_npoint(np.random.default_rng(5), _cam())
    keep = [0, 2, 6, 8, 4]
    v = assess_npoint(fit_npoint(uv[keep], xy[keep], "homography"), uv[keep], xy[keep], SIZE)
    assert "too_few_marks" in _codes(v)
    assert "at least 6" in v["problems"][0]["message"]


def test_marks_bunched_in_a_corner_are_not_spread() -> None:
    uv, xy, _ = simulate_npoint(np.random.default_rng(6), _cam(), field_mm=(16.0, 12.0))
    v = assess_npoint(fit_npoint(uv, xy, "affine"), uv, xy, SIZE)
    assert "marks_not_spread" in _codes(v), v
    # a mid-sized field passes with advice that the map extrapolates outside the marks
    uv, xy, _ = simulate_npoint(np.random.default_rng(6), _cam(), field_mm=(90.0, 60.0))
    v = assess_npoint(fit_npoint(uv, xy), uv, xy, SIZE)
    assert v["ok"] is True and [a["code"] for a in v["advice"]] == ["map_extrapolates"]


def test_marks_in_a_thin_strip_are_not_spread() -> None:
    uv, xy, _ = simulate_npoint(np.random.default_rng(7), _cam(), field_mm=(200.0, 8.0))
    v = assess_npoint(fit_npoint(uv, xy, "affine"), uv, xy, SIZE, steps=list(range(11, 20)))
    assert "marks_not_spread" in _codes(v)
