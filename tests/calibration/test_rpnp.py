"""RPnP (Li, Xu, Xie 2012): exact on exact data, truth within the reported uncertainty after the
refinement, the same optimum as SQPnP+LM, and clear errors on degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import transform_error
from calibration.pose import PoseEstimationError, RPnPError, estimate_pose_by, rpnp

CAM = CameraModel("opencv5", 1280, 960, np.array([[1200.0, 0, 641], [0, 1200, 479], [0, 0, 1]]),
                  np.array([-0.12, 0.03, 0.0005, -0.0003, 0.0]))


def _scene(rng: np.random.Generator, n: int, planar: bool, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    X = rng.uniform(-0.15, 0.15, (n, 3))
    if planar:
        X[:, 2] = 0.0
    R = Rotation.from_rotvec(rng.normal(0.0, 0.4, 3)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), distance_m]
    return X, T


@pytest.mark.parametrize("planar", [False, True])
def test_exact_data_exact_pose(planar: bool) -> None:
    rng = np.random.default_rng(3)
    for n in (4, 6, 25):
        X, T = _scene(rng, n, planar, 1.2)
        P = X @ T[:3, :3].T + T[:3, 3]
        R, t, cost = rpnp(X, P[:, :2] / P[:, 2:])[0]
        # the shared unknown is a double root of sum(f_j^2): about half the digits survive raw
        assert np.degrees(np.linalg.norm(Rotation.from_matrix(R.T @ T[:3, :3]).as_rotvec())) < 1e-2
        assert np.linalg.norm(t - T[:3, 3]) < 1e-5 and cost < 1e-12
        refined = estimate_pose_by(CAM, X, CAM.project(P), "rpnp")
        rot, trans = transform_error(refined.T_cam_target, T)
        assert rot < 1e-7 and trans < 1e-8  # LM's stopping tolerance on 4 coplanar points


@pytest.mark.parametrize("planar", [False, True])
def test_refined_truth_within_reported_uncertainty(planar: bool) -> None:
    """Over 40 noisy views the Mahalanobis distance of the error (6 dof) averages near 6."""
    rng = np.random.default_rng(7 + planar)
    d2 = []
    for _ in range(40):
        X, T = _scene(rng, 20, planar, rng.uniform(0.5, 2.0))
        uv = CAM.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.4, (20, 2))
        res = estimate_pose_by(CAM, X, uv, "rpnp")
        assert res.method == "rpnp"
        E = res.T_cam_target
        w = Rotation.from_matrix(T[:3, :3] @ E[:3, :3].T).as_rotvec()  # left perturbation: R_true = Exp(w) R
        e = np.concatenate([w, T[:3, 3] - E[:3, 3]])
        d2.append(float(e @ np.linalg.solve(res.covariance, e)))
    assert 3.0 < np.mean(d2) < 10.0, np.mean(d2)
    assert np.mean(np.array(d2) < 16.8) > 0.85  # chi2(6) 99 % quantile


def test_same_optimum_as_sqpnp() -> None:
    rng = np.random.default_rng(11)
    for planar in (False, True):
        X, T = _scene(rng, 12, planar, 1.5)
        uv = CAM.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, 0.5, (12, 2))
        a = estimate_pose_by(CAM, X, uv, "rpnp")
        b = estimate_pose_by(CAM, X, uv, "sqpnp")
        rot, trans = transform_error(a.T_cam_target, b.T_cam_target)
        assert rot < 1e-6 and trans < 1e-6
        assert abs(a.rms_px - b.rms_px) < 1e-6


def test_degenerate_inputs_answer_clear_errors() -> None:
    X = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]])
    xy = X[:, :2] / 1.0
    with pytest.raises(RPnPError, match="at least 4 points.*3 points give up to four poses"):
        rpnp(X, xy)
    line = np.column_stack([np.linspace(0, 0.3, 8), np.zeros(8), np.zeros(8)])
    with pytest.raises(RPnPError, match="collinear"):
        rpnp(line, line[:, :2] + [0.0, 0.01])
    with pytest.raises(RPnPError, match="5 target points but 4 image points"):
        rpnp(np.random.default_rng(0).uniform(size=(5, 3)), np.zeros((4, 2)))
    with pytest.raises(RPnPError, match="NaN"):
        rpnp(np.vstack([X, [np.nan, 0, 0]]), np.zeros((4, 2)))
    # through the pose API: the same reasons, as PoseEstimationError (a ValueError)
    with pytest.raises(PoseEstimationError, match="at least 4"):
        estimate_pose_by(CAM, X, np.array([[600.0, 400], [700, 400], [600, 500]]), "rpnp")
    uv = CAM.project(line + [0.0, 0.0, 1.0])
    with pytest.raises(PoseEstimationError, match="collinear"):
        estimate_pose_by(CAM, line, uv, "rpnp")
    X3, T = _scene(np.random.default_rng(1), 10, False, 1.0)
    with pytest.raises(PoseEstimationError, match="ippe needs coplanar"):
        estimate_pose_by(CAM, X3, CAM.project(X3 @ T[:3, :3].T + T[:3, 3]), "ippe")
    with pytest.raises(PoseEstimationError, match="unknown pose method"):
        estimate_pose_by(CAM, X3, CAM.project(X3 @ T[:3, :3].T + T[:3, 3]), "p3p")
