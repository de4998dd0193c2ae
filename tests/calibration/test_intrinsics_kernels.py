"""The compiled bundle kernels: analytic derivatives against central differences, the normal
equations against the dense Jacobians, and the linearised jackknife against re-solved replicates."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3
from calibration.intrinsics import kernels
from calibration.intrinsics.model import BundleProblem, camera_from_vector, intrinsic_steps, normal_equations_at
from calibration.intrinsics.uncertainty import cell_grid, jackknife_projection_rms, projection_difference
from calibration.intrinsics.views import collect_views, solve_views
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard

DIST = {"opencv5": [-0.28, 0.09, 0.0008, -0.0006, -0.015],
        "opencv8": [0.15, -0.1, 0.0008, -0.0006, 0.01, 0.45, -0.05, 0.02],
        "division": [-0.3]}


def _problem(model: str, rng: np.random.Generator) -> tuple[BundleProblem, np.ndarray, np.ndarray, np.ndarray]:
    c = np.array([800.0, 790.0, 320.0, 240.0, *DIST[model]])
    V, n = 3, 20
    X = np.column_stack([rng.uniform(-0.1, 0.1, (V * n, 2)), np.zeros(V * n)])
    R = exp_so3(rng.normal(0.0, 0.3, (V, 3)))
    t = np.column_stack([rng.normal(0.0, 0.05, (V, 2)), rng.uniform(0.4, 0.6, V)])
    view = np.repeat(np.arange(V), n).astype(np.int64)
    starts = np.arange(0, V * n + 1, n).astype(np.int64)
    p = BundleProblem(model, (640, 480), X, np.zeros((V * n, 2)), view, starts, rng.uniform(0.5, 2.0, V * n))
    p.obs = p.project(c, R, t) + rng.normal(0.0, 0.1, (V * n, 2))
    return p, c, R, t


@pytest.mark.parametrize("model", ["opencv5", "opencv8", "division"])
def test_analytic_jacobians_match_central_differences(model: str) -> None:
    rng = np.random.default_rng(3)
    p, c, R, t = _problem(model, rng)
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
        dv = np.tile(e6, (len(R), 1))
        Rp, tp = kernels.moved_poses(R, t, dv)
        Rm, tm = kernels.moved_poses(R, t, -dv)
        fd = (p.residuals(c, Rp, tp) - p.residuals(c, Rm, tm)) / (2 * h)
        assert np.allclose(Jp[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(Jp).max()), f"pose column {k}"


@pytest.mark.parametrize("model", ["opencv5", "division"])
def test_normal_blocks_are_the_dense_products(model: str) -> None:
    rng = np.random.default_rng(4)
    p, c, R, t = _problem(model, rng)
    free = np.ones(len(c), dtype=bool)
    n, r = normal_equations_at(p, c, R, t, free)
    Jc, Jp = kernels.point_jacobians(p.model_id, c, R, t, p.X, p.weights(), p.view)
    assert np.allclose(n.A, Jc.T @ Jc, rtol=1e-10)
    assert np.allclose(n.gc, Jc.T @ r, rtol=1e-10)
    for k in range(p.n_views):
        rows = slice(2 * p.starts[k], 2 * p.starts[k + 1])
        assert np.allclose(n.D[k], Jp[rows].T @ Jp[rows], rtol=1e-10)
        assert np.allclose(n.B[k], Jc[rows].T @ Jp[rows], rtol=1e-10)


def test_a_point_behind_the_camera_makes_the_cost_infinite() -> None:
    rng = np.random.default_rng(5)
    p, c, R, t = _problem("opencv5", rng)
    t = t.copy()
    t[0, 2] = -1.0
    r = p.residuals(c, R, t)
    assert np.isnan(r[: 2 * p.starts[1]]).all() and np.isfinite(r[2 * p.starts[1]:]).all()


def test_linearised_jackknife_agrees_with_re_solved_replicates() -> None:
    """The influence-function jackknife (one Gauss-Newton step per replicate) against the
    delete-a-group jackknife that re-solves every replicate, on the same cells."""
    W, H = 960, 720
    cam = CameraModel("opencv5", W, H, np.array([[800.0, 0, 483.0], [0, 798.0, 356.0], [0, 0, 1]]),
                      np.array(DIST["opencv5"]))
    board = Chessboard(9, 6, 25.0)
    rng = np.random.default_rng(11)
    dets = synthetic_detections(cam, board, plan_views(cam, board, 12, rng, fill=0.5), 0.2, rng)
    views, _, size = collect_views(dets, board, None)
    p, c, R, t, _ = solve_views("opencv5", size, views, board)
    n, _ = normal_equations_at(p, c, R, t, np.ones(len(c), dtype=bool))
    grid, _, _ = cell_grid(size, 16)
    pts = grid[::3]
    full = camera_from_vector("opencv5", size, c)
    lin = jackknife_projection_rms(full, n, pts, groups=6)
    qs = []
    for g in range(6):
        keep = [k for k in range(len(views)) if k % 6 != g]
        _, cg, _, _, _ = solve_views("opencv5", size, [views[k] for k in keep], board, start=(c, R[keep], t[keep]))
        qs.append(projection_difference(camera_from_vector("opencv5", size, cg), full, pts)["diff_px"])
    Q = np.array(qs)
    dev = Q - Q.mean(axis=0)
    solved = float(np.sqrt(np.mean(5 / 6 * np.sum(dev * dev, axis=(0, 2)))))
    assert lin > 0 and 0.8 < lin / solved < 1.25, (lin, solved)
