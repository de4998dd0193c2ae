"""The fisheye4 (Kannala-Brandt) lens model: projection against OpenCV's cv2.fisheye, the round
trip through unprojection, the solver's analytic derivatives, and a wide lens it fits where
opencv5 cannot, chosen by cross-validation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3
from calibration.intrinsics import calibrate, covered_points, kernels, projection_difference, select_by_cross_validation
from calibration.intrinsics.model import BundleProblem, intrinsic_steps
from calibration.io.export import ExportError, write_opencv_yaml
from calibration.observations import Detection
from calibration.synthetic import plan_views
from calibration.targets import Chessboard

K = np.array([[420.0, 0, 640.0], [0, 421.0, 480.0], [0, 0, 1]])
FISHEYE = CameraModel("fisheye4", 1280, 960, K, np.array([0.05, -0.02, 0.01, -0.002]))


def test_projection_matches_opencv_fisheye_and_round_trips() -> None:
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, np.radians(80), 200)
    az = rng.uniform(0, 2 * np.pi, 200)
    P = np.column_stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)])
    ours = FISHEYE.project(P)
    cv, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, FISHEYE.dist)
    assert np.abs(ours - cv.reshape(-1, 2)).max() < 1e-6
    rays = FISHEYE.unproject(ours)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    assert np.abs(rays - P).max() < 1e-9
    assert np.all(np.isnan(FISHEYE.unproject([[1e6, 480.0]])[:, :2]))   # beyond what the lens can see


def test_fisheye4_derivatives_match_central_differences() -> None:
    rng = np.random.default_rng(3)
    c = np.array([420.0, 421.0, 640.0, 480.0, 0.05, -0.02, 0.01, -0.002])
    V, n = 3, 20
    X = np.column_stack([rng.uniform(-0.3, 0.3, (V * n, 2)), np.zeros(V * n)])
    X[0, :2] = 0.0   # one point on the axis: the series branch
    R = exp_so3(rng.normal(0.0, 0.3, (V, 3)))
    R[0] = np.eye(3)
    t = np.column_stack([rng.normal(0.0, 0.05, (V, 2)), rng.uniform(0.2, 0.3, V)])
    t[0, :2] = 0.0
    view = np.repeat(np.arange(V), n).astype(np.int64)
    p = BundleProblem("fisheye4", (1280, 960), X, np.zeros((V * n, 2)), view,
                      np.arange(0, V * n + 1, n).astype(np.int64))
    p.obs = p.project(c, R, t) + rng.normal(0.0, 0.1, (V * n, 2))
    assert np.abs(p.project(c, R, t) - FISHEYE.project(np.einsum("vij,vnj->vni", R, X.reshape(V, n, 3)).reshape(-1, 3)
                                                       + np.repeat(t, n, axis=0))).max() < 1e-9
    Jc, Jp = kernels.point_jacobians(p.model_id, c, R, t, p.X, p.weights(), p.view)
    hs = intrinsic_steps(c)
    for i in range(len(c)):
        e = np.zeros_like(c)
        e[i] = hs[i]
        fd = (p.residuals(c + e, R, t) - p.residuals(c - e, R, t)) / (2 * hs[i])
        assert np.allclose(Jc[:, i], fd, rtol=1e-5, atol=1e-6 * np.abs(Jc).max()), f"column {i}"
    h = 1e-7
    for k in range(6):
        e6 = np.zeros(6)
        e6[k] = h
        Rp, tp = kernels.moved_poses(R, t, np.tile(e6, (V, 1)))
        Rm, tm = kernels.moved_poses(R, t, np.tile(-e6, (V, 1)))
        fd = (p.residuals(c, Rp, tp) - p.residuals(c, Rm, tm)) / (2 * h)
        assert np.allclose(Jp[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(Jp).max()), f"pose column {k}"


def _views(cam: CameraModel, board: Chessboard, n: int, seed: int) -> list[Detection]:
    rng = np.random.default_rng(seed)
    tp = board.points()
    out = []
    for k, T in enumerate(plan_views(cam, board, n, rng, fill=0.6, margin_px=6, whole_outline=True)):
        uv = cam.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.05, (len(tp.ids), 2))
        out.append(Detection(f"v{k:02d}", True, ids=tp.ids.copy(), uv=uv, image_size=cam.size))
    return out


@pytest.mark.slow
def test_a_wide_lens_is_fitted_and_chosen_by_cross_validation() -> None:
    board = Chessboard(9, 6, 40.0)
    dets = _views(FISHEYE, board, 16, seed=5)
    res = calibrate(dets, board, "fisheye4")
    pts = covered_points(res)
    assert res.rms_px < 0.08
    assert projection_difference(res.camera, FISHEYE, pts)["rms_px"] < 0.1
    chosen, sel = select_by_cross_validation(dets, board, [("opencv5", False), ("fisheye4", False)])
    assert sel["chosen"]["model"] == "fisheye4" and chosen.camera.model == "fisheye4"
    by = {r["model"]: r for r in sel["candidates"]}
    assert by["fisheye4"]["cross_validation_px"] < 0.9 * by["opencv5"]["cross_validation_px"]


def test_opencv_export_refuses_fisheye4(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ExportError, match="fisheye4"):
        write_opencv_yaml(FISHEYE, tmp_path / "f.yaml")


def test_a_fisheye4_camera_maps_pixels_to_the_plane_and_back_through_its_file() -> None:
    from calibration.geometry import make_transform
    from calibration.measure.plane import image_to_plane, plane_to_image

    cam = CameraModel.from_dict(FISHEYE.to_dict())          # through the cam.json form
    assert cam.model == "fisheye4" and np.allclose(cam.dist, FISHEYE.dist)
    T = make_transform(exp_so3(np.array([[0.5, -0.3, 0.1]]))[0], np.array([0.02, -0.01, 0.3]))
    xy = np.random.default_rng(2).uniform(-0.2, 0.2, (50, 2))
    uv = plane_to_image(cam, T, xy)
    ok = np.all(np.isfinite(uv), axis=1)
    assert ok.sum() > 40
    assert np.abs(image_to_plane(cam, T, uv[ok])[:, :2] - xy[ok]).max() < 1e-9


@pytest.mark.slow   # 20 calibrations of 12 synthetic views
def test_fisheye4_uncertainty_is_honest_over_20_seeds() -> None:
    """The pooled actual / reported projection error (RMS over RMS, as
    test_uncertainty_honesty_seeds) is within 0.5-2 over 20 seeded sets of independent 0.1 px
    corner noise."""
    from calibration.intrinsics import covered_point_means

    board = Chessboard(9, 6, 40.0)
    act, rep = [], []
    for seed in range(1000, 1020):
        rng = np.random.default_rng(seed)
        tp = board.points()
        dets = []
        for k, T in enumerate(plan_views(FISHEYE, board, 12, rng, fill=0.6, margin_px=6, whole_outline=True)):
            uv = FISHEYE.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.1, (len(tp.ids), 2))
            dets.append(Detection(f"v{k}", True, ids=tp.ids.copy(), uv=uv, image_size=FISHEYE.size))
        res = calibrate(dets, board, "fisheye4")
        act.append(projection_difference(res.camera, FISHEYE, covered_point_means(res))["rms_px"])
        rep.append(res.uncertainty["projection_rms_px"])
    ratio = np.sqrt(np.mean(np.square(act))) / np.sqrt(np.mean(np.square(rep)))
    assert 0.5 <= ratio <= 2.0, ratio
