"""DLT on a 3D target: recovers the camera; coplanar or too few points refused."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, look_at, transform_error
from calibration.pose import DLTError, calibrate_dlt

K = np.array([[1200.0, 0, 650], [0, 1195, 470], [0, 0, 1]])


def _scene(cam: CameraModel, n: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-0.15, 0.15, n), rng.uniform(-0.12, 0.12, n), rng.uniform(0, 0.12, n)])
    T = invert(look_at([0.15, -0.25, -0.55], [0.0, 0.0, 0.06], up=[0, -1, 0]))
    uv = cam.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, noise, (n, 2))
    return X, uv, T


def test_pinhole_exact() -> None:
    cam = CameraModel("opencv5", 1300, 940, K, np.zeros(5))
    X, uv, T = _scene(cam, 8, 0, 0.0)
    res = calibrate_dlt(X, uv, (1300, 940), distortion=False)
    assert np.allclose(res.camera.K, K, atol=1e-5)
    rot, trans = transform_error(res.T_cam_target, T)
    assert rot < 1e-8 and trans < 1e-8


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_distorted_with_noise_within_uncertainty(seed: int) -> None:
    cam = CameraModel("opencv5", 1300, 940, K, np.array([-0.15, 0.0, 0.0, 0.0, 0.0]))
    X, uv, T = _scene(cam, 60, seed, 0.1)
    res = calibrate_dlt(X, uv, (1300, 940))
    assert res.free_params == ["fx", "fy", "cx", "cy", "k1", "k2"]
    sig = np.sqrt(np.diag(res.covariance))
    assert abs(res.camera.fx - 1200) < 4 * sig[0]
    assert abs(res.camera.cx - 650) < 4 * sig[2]
    assert res.rms_px < 0.2
    out = res.to_json()
    assert out["model"] == "opencv5" and "T_cam_target" in out


def test_division_model() -> None:
    cam = CameraModel("division", 1300, 940, K, np.array([-0.2]))
    X, uv, _ = _scene(cam, 30, 4, 0.0)
    res = calibrate_dlt(X, uv, (1300, 940), model="division")
    assert res.camera.dist[0] == pytest.approx(-0.2, abs=1e-6)


def test_refusals() -> None:
    cam = CameraModel("opencv5", 1300, 940, K, np.zeros(5))
    X, uv, _ = _scene(cam, 20, 5, 0.0)
    flat = X.copy()
    flat[:, 2] = 0.0
    with pytest.raises(DLTError, match="coplanar"):
        calibrate_dlt(flat, uv)
    with pytest.raises(DLTError, match="at least 6"):
        calibrate_dlt(X[:5], uv[:5])
    with pytest.raises(DLTError, match="image points"):
        calibrate_dlt(X, uv[:10])
    with pytest.raises(DLTError, match="opencv5 and division"):
        calibrate_dlt(X, uv, model="opencv8")
