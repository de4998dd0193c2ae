"""The board warp (a target that is not flat, mrcal's two-parameter bow): its analytic derivatives,
its recovery from views of a bowed board, and the flat solve it leaves unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3
from calibration.intrinsics import calibrate, covered_points, kernels, projection_difference
from calibration.intrinsics.model import BundleProblem, intrinsic_steps
from calibration.intrinsics.views import warp_basis
from calibration.observations import Detection
from calibration.synthetic import plan_views
from calibration.targets import Chessboard

BOARD = Chessboard(9, 6, 30.0)
TRUTH = CameraModel("opencv5", 960, 720, np.array([[800.0, 0, 483.0], [0, 798.0, 356.0], [0, 0, 1]]),
                    np.array([-0.28, 0.09, 0.0008, -0.0006, -0.015]))


@pytest.mark.parametrize("model", ["opencv5", "opencv8", "division"])
def test_warp_derivatives_match_central_differences(model: str) -> None:
    rng = np.random.default_rng(7)
    dist = {"opencv5": [-0.2, 0.05, 0.001, -0.001, 0.0], "opencv8": [0.1, -0.1, 0.001, 0.0, 0.01, 0.4, -0.05, 0.02],
            "division": [-0.3]}[model]
    c = np.array([800.0, 790.0, 320.0, 240.0, *dist, 0.004, -0.002])
    V, n = 3, 20
    X = np.column_stack([rng.uniform(-0.1, 0.1, (V * n, 2)), np.zeros(V * n), rng.uniform(0, 1, (V * n, 2))])
    R = exp_so3(rng.normal(0.0, 0.3, (V, 3)))
    t = np.column_stack([rng.normal(0.0, 0.05, (V, 2)), rng.uniform(0.4, 0.6, V)])
    view = np.repeat(np.arange(V), n).astype(np.int64)
    p = BundleProblem(model, (640, 480), X, np.zeros((V * n, 2)), view, np.arange(0, V * n + 1, n).astype(np.int64))
    p.obs = p.project(c, R, t) + rng.normal(0.0, 0.1, (V * n, 2))
    Jc, Jp = kernels.point_jacobians(p.model_id, c, R, t, p.X, p.weights(), p.view)
    hs = intrinsic_steps(c)
    for i in (len(c) - 2, len(c) - 1):
        e = np.zeros_like(c)
        e[i] = hs[i]
        fd = (p.residuals(c + e, R, t) - p.residuals(c - e, R, t)) / (2 * hs[i])
        assert np.abs(Jc[:, i]).max() > 1.0          # the warp moves the points
        assert np.allclose(Jc[:, i], fd, rtol=1e-5, atol=1e-6 * np.abs(Jc).max()), f"column {i}"
    h = 1e-7
    for k in range(6):   # the pose derivatives see the warped point
        e6 = np.zeros(6)
        e6[k] = h
        Rp, tp = kernels.moved_poses(R, t, np.tile(e6, (V, 1)))
        Rm, tm = kernels.moved_poses(R, t, np.tile(-e6, (V, 1)))
        fd = (p.residuals(c, Rp, tp) - p.residuals(c, Rm, tm)) / (2 * h)
        assert np.allclose(Jp[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(Jp).max()), f"pose column {k}"


def _bowed_views(warp_m: tuple[float, float], seed: int) -> list[Detection]:
    rng = np.random.default_rng(seed)
    tp = BOARD.points()
    X = tp.xyz_m.copy()
    X[:, 2] += warp_basis(BOARD, X) @ np.asarray(warp_m)
    out = []
    for k, T in enumerate(plan_views(TRUTH, BOARD, 14, rng, fill=0.6, margin_px=6, whole_outline=True)):
        uv = TRUTH.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.05, (len(X), 2))
        out.append(Detection(f"v{k:02d}", True, ids=tp.ids.copy(), uv=uv, image_size=(960, 720)))
    return out


def test_a_bowed_board_is_recovered_and_the_camera_with_it() -> None:
    dets = _bowed_views((0.0015, -0.0008), seed=11)   # 1.5 mm and -0.8 mm bows
    flat = calibrate(dets, BOARD, "opencv5")
    bowed = calibrate(dets, BOARD, "opencv5", board_warp=True)
    assert bowed.board_warp is not None and flat.board_warp is None
    h, s = np.array(bowed.board_warp["height_mm"]), np.array(bowed.board_warp["sigma_mm"])
    assert np.all(np.abs(h - [1.5, -0.8]) < np.maximum(4 * s, 0.05)), (h, s)
    pts = covered_points(bowed)
    err_bowed = projection_difference(bowed.camera, TRUTH, pts)["rms_px"]
    err_flat = projection_difference(flat.camera, TRUTH, pts)["rms_px"]
    assert err_bowed < 0.5 * err_flat, (err_bowed, err_flat)
    assert bowed.rms_px < 0.08 < flat.rms_px
    assert bowed.param_names == flat.param_names and bowed.covariance.shape == flat.covariance.shape
    assert "board_warp" in bowed.to_json() and "board_warp" not in flat.to_json()


def test_a_flat_board_gets_a_warp_of_zero_within_its_sigma() -> None:
    dets = _bowed_views((0.0, 0.0), seed=12)
    res = calibrate(dets, BOARD, "opencv5", board_warp=True)
    assert res.board_warp is not None
    h, s = np.array(res.board_warp["height_mm"]), np.array(res.board_warp["sigma_mm"])
    assert np.all(np.abs(h) < 4 * s + 1e-3), (h, s)
