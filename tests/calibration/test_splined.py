"""The splined stereographic lens model (mrcal's, order 3): projection and Newton unprojection, the
solver's analytic Jacobian, the cam.json form, mapping through it, the refusal on small sets (also
inside the cross-validated selection), the exports' refusal, a wide lens fitted, and its
uncertainty's honesty over 20 seeds."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import splined
from calibration.camera_model import CameraModel, CameraModelError
from calibration.geometry import exp_so3, make_transform
from calibration.intrinsics import (
    CrossValidationError,
    IntrinsicsError,
    calibrate,
    covered_point_means,
    projection_difference,
    select_by_cross_validation,
)
from calibration.intrinsics.splined_problem import _Problem
from calibration.intrinsics.splined_solver import calibrate_splined
from calibration.io.export import ExportError, write_opencv_yaml, write_ros_yaml
from calibration.observations import Detection
from calibration.synthetic import plan_views
from calibration.targets import Chessboard

K = np.array([[420.0, 0, 640.0], [0, 421.0, 480.0], [0, 0, 1]])
FISHEYE = CameraModel("fisheye4", 1280, 960, K, np.array([0.05, -0.02, 0.01, -0.002]))
BOARD = Chessboard(9, 6, 40.0)


def _splined_camera(seed: int = 0, scale: float = 0.01) -> CameraModel:
    lay = splined.SplineLayout(10, 8, 150.0)
    ctrl = np.random.default_rng(seed).normal(0.0, scale, 2 * lay.n_ctrl)
    return CameraModel("splined", 1280, 960, K, np.concatenate([lay.header(), ctrl]))


def _views(cam: CameraModel, n: int, seed: int, noise_px: float = 0.1) -> list[Detection]:
    rng = np.random.default_rng(seed)
    tp = BOARD.points()
    out = []
    for k, T in enumerate(plan_views(cam, BOARD, n, rng, fill=0.6, margin_px=6, whole_outline=True)):
        uv = cam.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, noise_px, (len(tp.ids), 2))
        out.append(Detection(f"v{k}", True, ids=tp.ids.copy(), uv=uv, image_size=cam.size))
    return out


def test_projection_round_trips_through_newton_unprojection_and_the_file() -> None:
    cam = CameraModel.from_dict(_splined_camera().to_dict())
    assert cam.model == "splined" and cam.dist.size == splined.n_dist(10, 8)
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, np.radians(70), 300)
    az = rng.uniform(0, 2 * np.pi, 300)
    P = np.column_stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)])
    uv = cam.project(P)
    rays = cam.unproject(uv)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    assert np.abs(rays - P).max() < 1e-9
    # with no correction the model is the stereographic projection: 2 tan(theta / 2)
    plain = CameraModel("splined", 1280, 960, K, np.concatenate([[10, 8, 150.0], np.zeros(160)]))
    r = np.hypot(*((plain.project(P) - K[:2, 2]) / [420.0, 421.0]).T)
    assert np.allclose(r, 2 * np.tan(ang / 2), atol=1e-12)
    # a ray at 90 deg or beyond cannot be unprojected to [x, y, 1]
    assert np.all(np.isnan(plain.unproject([[640.0 + 420.0 * 2.5, 480.0]])[:, :2]))


def test_a_malformed_splined_description_is_refused() -> None:
    with pytest.raises(CameraModelError, match="splined"):
        CameraModel("splined", 1280, 960, K, np.array([10, 8, 150.0, 0.0, 0.0]))
    with pytest.raises(CameraModelError, match="4 x 4"):
        CameraModel("splined", 1280, 960, K, np.concatenate([[3, 8, 150.0], np.zeros(48)]))


def test_the_solver_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(0)
    lay = splined.SplineLayout(8, 7, 150)
    X = np.column_stack([rng.uniform(-0.2, 0.2, (20, 2)), np.zeros(20)])
    V = 3
    R = exp_so3(rng.normal(0, 0.3, (V, 3)))
    t = np.column_stack([rng.normal(0, 0.05, (V, 2)), np.full(V, 0.5)])
    prob = _Problem(lay, np.vstack([X] * V), np.zeros((20 * V, 2)), np.repeat(np.arange(V), 20), V)
    x = np.concatenate([[400.0, 410.0, 640.0, 480.0], rng.normal(0, 0.02, 2 * lay.n_ctrl)])
    _, J = prob.project(x, R, t, jac=True)
    assert J is not None
    Jd = J.toarray()
    h = 1e-6
    for i in list(range(6)) + list(range(prob.n_intr - 3, prob.n)):
        dx = np.zeros(prob.n)
        dx[i] = h
        plus, minus = prob.step(x, R, t, dx), prob.step(x, R, t, -dx)
        num = (prob.project(*plus)[0] - prob.project(*minus)[0]).ravel() / (2 * h)
        assert np.abs(num - Jd[:, i]).max() < 1e-5 * max(1.0, np.abs(Jd[:, i]).max()), i


def test_a_splined_camera_maps_pixels_to_the_plane_and_back() -> None:
    from calibration.measure.plane import image_to_plane, plane_to_image

    cam = _splined_camera(2)
    T = make_transform(exp_so3(np.array([[0.4, -0.3, 0.1]]))[0], np.array([0.02, -0.01, 0.3]))
    xy = np.random.default_rng(2).uniform(-0.2, 0.2, (50, 2))
    uv = plane_to_image(cam, T, xy)
    ok = np.all(np.isfinite(uv), axis=1)
    assert ok.sum() > 40
    assert np.abs(image_to_plane(cam, T, uv[ok])[:, :2] - xy[ok]).max() < 1e-9


def test_opencv_and_ros_exports_refuse_the_splined_model(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ExportError, match="splined"):
        write_opencv_yaml(_splined_camera(), tmp_path / "c.yaml")
    with pytest.raises(ExportError, match="splined"):
        write_ros_yaml(_splined_camera(), tmp_path / "r.yaml")


def test_a_small_set_is_refused_with_the_reason_also_by_the_selection() -> None:
    dets = _views(FISHEYE, 14, seed=3)
    with pytest.raises(IntrinsicsError, match="at least 40 views"):
        calibrate(dets, BOARD, "splined")
    # the selection refuses the candidate with that reason (alone here: nothing else to choose)
    with pytest.raises(CrossValidationError, match="splined: the splined model needs at least 40 views"):
        select_by_cross_validation(dets, BOARD, [("splined", False)])


@pytest.mark.slow   # 48 views: a fisheye4 start, then the splined solve
def test_a_wide_lens_is_fitted_to_the_noise() -> None:
    dets = _views(FISHEYE, 48, seed=5)
    res = calibrate(dets, BOARD, "splined")
    assert res.camera.model == "splined"
    assert res.rms_px < 0.16                      # 0.1 px per coordinate: 0.141 px per corner
    assert projection_difference(res.camera, FISHEYE, covered_point_means(res))["rms_px"] < 0.2
    assert res.to_json()["parameters"]["names"][:7] == ["fx", "fy", "cx", "cy", "Nx", "Ny", "fov_x_deg"]


@pytest.mark.slow   # 20 splined calibrations of 12 synthetic views
def test_splined_uncertainty_is_honest_over_20_seeds() -> None:
    """Pooled actual / reported projection error (RMS over RMS, at the covered cells' point means)
    within 0.5-2 over 20 seeded sets of a fisheye4 lens (which the spline only approximates) with
    independent 0.1 px corner noise; the 40-view rule is off (``check=False``, the coarsest grid)."""
    act, rep = [], []
    for seed in range(20):
        res = calibrate_splined(_views(FISHEYE, 12, seed=1000 + seed), BOARD, check=False)
        act.append(projection_difference(res.camera, FISHEYE, covered_point_means(res))["rms_px"])
        rep.append(res.uncertainty["projection_rms_px"])
    ratio = np.sqrt(np.mean(np.square(act))) / np.sqrt(np.mean(np.square(rep)))
    assert 0.5 <= ratio <= 2.0, ratio


def test_the_projection_jacobian_for_the_uncertainty_matches_central_differences() -> None:
    from calibration.intrinsics.model import intrinsic_steps, intrinsics_vector, project_normalized
    from calibration.intrinsics.uncertainty import projection_jacobians

    cam = _splined_camera(3)
    pts = np.random.default_rng(0).uniform([100, 100], [1100, 800], (30, 2))
    Ja, _, valid = projection_jacobians(cam, pts)
    assert valid.all()
    xy = cam.unproject(pts)[:, :2]
    c = intrinsics_vector(cam)
    hs = intrinsic_steps(c)
    for i in [0, 1, 2, 3, *range(7, len(c), 7)]:
        e = np.zeros_like(c)
        e[i] = hs[i]
        num = ((project_normalized(cam.model, c + e, xy) - project_normalized(cam.model, c - e, xy)) / (2 * hs[i]))
        assert np.abs(num.reshape(-1) - Ja[:, i]).max() < 1e-4 * max(1.0, np.abs(Ja[:, i]).max()), i
    assert not Ja[:, 4:7].any()       # the grid's layout is fixed


def test_the_board_warp_jacobian_matches_central_differences() -> None:
    """The splined solve with the target's two warp heights (mrcal solves them with its splined
    model too): their Jacobian columns are exact (the solve on real data: bench/intrinsics_splined.py)."""
    from calibration.intrinsics.views import warp_basis

    rng = np.random.default_rng(1)
    lay = splined.SplineLayout(8, 7, 150)
    V = 3
    X = np.vstack([BOARD.points().xyz_m[:20]] * V)
    R = exp_so3(rng.normal(0, 0.3, (V, 3)))
    t = np.column_stack([rng.normal(0, 0.05, (V, 2)), np.full(V, 0.5)])
    prob = _Problem(lay, X, np.zeros((len(X), 2)), np.repeat(np.arange(V), 20), V, warp_basis(BOARD, X))
    prob.wp = np.array([0.002, -0.001])
    x = np.concatenate([[400.0, 410.0, 640.0, 480.0], rng.normal(0, 0.02, 2 * lay.n_ctrl)])
    _, J = prob.project(x, R, t, jac=True)
    assert J is not None and J.shape[1] == prob.n
    Jd = J.toarray()
    h = 1e-7
    for i in (prob.n - 2, prob.n - 1):
        dx = np.zeros(prob.n)
        dx[i] = h
        plus, minus = prob.step(x, R, t, dx), prob.step(x, R, t, -dx)
        num = (prob.project(*plus)[0] - prob.project(*minus)[0]).ravel() / (2 * h)
        assert np.abs(num).max() > 1.0 and np.abs(num - Jd[:, i]).max() < 1e-4 * np.abs(Jd[:, i]).max(), i


def test_outlier_points_are_weighted_out_only_where_the_stated_precision_explains_the_residuals() -> None:
    """The splined solver's point rule is the parametric solver's (``views.outlier_points``): a
    5-sigma point is a detection failure (weighted out) only where the detectors' stated precision
    explains the residual scale; without a stated precision, or with residuals far beyond it (a lens
    the model does not fit at the image's edge), it is only flagged."""
    from calibration.intrinsics.views import collect_views, outlier_points

    dets = _views(FISHEYE, 3, 7)
    rng = np.random.default_rng(3)
    n = sum(len(d.uv) for d in dets)
    res = rng.normal(0.0, 0.1, (n, 2))
    res[5] = [3.0, -2.0]                                   # one corner 36 sigma off
    w0 = np.ones(n)
    views, _, _ = collect_views(dets, BOARD, FISHEYE.size)
    out, reject = outlier_points(res, w0 > 0, views)
    assert out[5] and out.sum() == 1 and not reject       # no stated precision: flagged only
    stated = [Detection(d.image, True, ids=d.ids, uv=d.uv, image_size=d.image_size,
                        uv_sigma_px=np.full(len(d.uv), 0.1)) for d in dets]
    views, _, _ = collect_views(stated, BOARD, FISHEYE.size)
    out, reject = outlier_points(res, w0 > 0, views)
    assert out[5] and out.sum() == 1 and reject           # the residuals are the stated noise: weighted out
    out, reject = outlier_points(10.0 * res, w0 > 0, views)
    assert out[5] and not reject                          # 10x the stated noise: misfit, flagged only
