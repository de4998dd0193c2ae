"""N-point: model selection by leave-one-out, reflections, HALCON parameters, bad layouts refused."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.npoint import NPointError, NPointResult, affine_par, apply_h, fit_npoint
from calibration.synthetic import simulate_npoint


def _cam(aspect: float = 1.0) -> CameraModel:
    return CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 960], [0, 1900.0 * aspect, 600], [0, 0, 1]]),
                       np.zeros(5))


def _field_error(res: NPointResult, uv: np.ndarray, truth) -> float:
    g = np.stack(np.meshgrid(np.linspace(uv[:, 0].min(), uv[:, 0].max(), 25),
                             np.linspace(uv[:, 1].min(), uv[:, 1].max(), 25)), -1).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((res.map(g) - truth(g)) ** 2, axis=1))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tilted_camera_picks_homography(seed: int) -> None:
    uv, xy, truth = simulate_npoint(np.random.default_rng(seed), _cam(), tilt_deg=1.5)
    res = fit_npoint(uv, xy)
    assert res.model == "homography"
    assert set(res.loo_rms_mm) == {"similarity", "affine", "homography"}
    assert res.loo_rms_mm["affine"] > 3 * res.loo_rms_mm["homography"]
    assert res.reflection  # image y down, robot y up
    assert _field_error(res, uv, truth) < 0.06
    assert 0.0 < res.field_sigma_mm["max"] < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_untilted_camera_picks_affine(seed: int) -> None:
    # non-square pixels (fy = 1.006 fx): an affine, not a similarity, and no perspective
    uv, xy, truth = simulate_npoint(np.random.default_rng(seed), _cam(1.006), tilt_deg=0.0)
    res = fit_npoint(uv, xy)
    assert res.model == "affine"
    assert _field_error(res, uv, truth) < 0.05


def test_similarity_allows_reflection() -> None:
    uv, xy, truth = simulate_npoint(np.random.default_rng(5), _cam(), tilt_deg=0.0, pixel_sigma_px=0.0,
                                    jog_sigma_mm=0.0)
    res = fit_npoint(uv, xy, model="similarity")
    assert res.reflection
    assert res.rms_mm < 1e-6
    assert any("reflection" in n for n in res.notes)


def test_halcon_affine_parameters() -> None:
    sx, sy, phi, theta, tx, ty = 0.25, 0.26, np.radians(20.0), np.radians(3.0), 100.0, -50.0
    R = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    slant = np.array([[1.0, -np.sin(theta)], [0.0, np.cos(theta)]])
    H = np.eye(3)
    H[:2, :2] = R @ slant @ np.diag([sx, sy])
    H[:2, 2] = [tx, ty]
    p = affine_par(H)
    assert p["sx"] == pytest.approx(sx) and p["sy"] == pytest.approx(sy)
    assert p["phi_deg"] == pytest.approx(20.0) and p["theta_deg"] == pytest.approx(3.0)
    assert p["tx_mm"] == pytest.approx(tx) and p["ty_mm"] == pytest.approx(ty)
    H_ref = H @ np.diag([1.0, -1.0, 1.0])  # a reflection shows as |theta| > 90 deg
    assert abs(affine_par(H_ref)["theta_deg"]) > 90.0


def test_undistortion_with_camera() -> None:
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 960], [0, 1900.0, 600], [0, 0, 1]]),
                      np.array([-0.25, 0.1, 0.0, 0.0, 0.0]))
    uv, xy, truth = simulate_npoint(np.random.default_rng(3), cam, tilt_deg=1.5, n_side=4)
    with_cam = fit_npoint(uv, xy, model="homography", camera=cam)
    without = fit_npoint(uv, xy, model="homography")
    assert _field_error(with_cam, uv, truth) < 0.5 * _field_error(without, uv, truth)
    again = NPointResult.from_json(with_cam.to_json())
    assert np.allclose(again.map(uv[:3]), with_cam.map(uv[:3]))


def test_collinear_marks_refused() -> None:
    uv = np.array([[100.0, 100.0], [200.0, 200.0], [300.0, 300.0], [400.0, 400.0]])
    xy = np.array([[0.0, 0.0], [10.0, -10.0], [20.0, -20.0], [30.0, -30.0]])
    with pytest.raises(NPointError, match="collinear"):
        fit_npoint(uv, xy)


def test_duplicate_marks_refused() -> None:
    uv = np.array([[100.0, 100.0], [500.0, 120.0], [100.2, 100.1], [300.0, 600.0]])
    xy = np.array([[0.0, 0.0], [100.0, 0.0], [50.0, 50.0], [50.0, -100.0]])
    with pytest.raises(NPointError, match="pairs 1 and 3"):
        fit_npoint(uv, xy)


def test_too_few_and_unknown_model_refused() -> None:
    with pytest.raises(NPointError, match="at least 3"):
        fit_npoint([[0, 0], [1, 1]], [[0, 0], [1, 1]])
    uv, xy, _ = simulate_npoint(np.random.default_rng(1), _cam())
    with pytest.raises(NPointError, match="model must be one of"):
        fit_npoint(uv, xy, model="projective")
    with pytest.raises(NPointError, match="needs at least 4"):
        fit_npoint(uv[[0, 1, 3]], xy[[0, 1, 3]], model="homography")


def test_map_matches_h() -> None:
    uv, xy, _ = simulate_npoint(np.random.default_rng(2), _cam(), tilt_deg=1.0)
    res = fit_npoint(uv, xy, model="affine")
    assert np.allclose(res.map(uv), apply_h(res.H, uv))
    js = res.to_json()
    assert {"model", "H", "rms_mm", "affine"} <= set(js)
    assert set(js["affine"]) == {"sx", "sy", "phi_deg", "theta_deg", "tx_mm", "ty_mm"}
