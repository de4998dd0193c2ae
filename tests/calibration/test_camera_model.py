"""Camera models: projection round trips, undistortion maps, HALCON conversion."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel, CameraModelError

K = np.array([[900.0, 0.0, 330.0], [0.0, 905.0, 238.0], [0.0, 0.0, 1.0]])
CAMS = [
    CameraModel("opencv5", 640, 480, K, np.array([-0.3, 0.1, 0.001, -0.002, -0.02])),
    CameraModel("opencv8", 640, 480, K, np.array([0.2, -0.05, 0.001, 0.0005, 0.002, 0.5, -0.02, 0.01])),
    CameraModel("division", 640, 480, K, np.array([-0.25])),
]


@pytest.mark.parametrize("cam", CAMS, ids=lambda c: c.model)
def test_project_unproject_round_trip(cam: CameraModel) -> None:
    uu, vv = np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 479, 7))
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    rays = cam.unproject(uv)
    assert np.allclose(cam.project(rays * 2.5), uv, atol=1e-7)
    und = cam.undistort_points(uv)
    ideal = CameraModel("opencv5", 640, 480, K, np.zeros(5))
    assert np.allclose(ideal.project(rays), und, atol=1e-7)


@pytest.mark.parametrize("cam", CAMS, ids=lambda c: c.model)
def test_undistortion_maps_match_projection(cam: CameraModel) -> None:
    mu, mv = cam.undistortion_maps()
    for u, v in [(10, 20), (320, 240), (600, 450)]:
        x = (u - K[0, 2]) / K[0, 0]
        y = (v - K[1, 2]) / K[1, 1]
        q = cam.project([[x, y, 1.0]])[0]
        assert q == pytest.approx([mu[v, u], mv[v, u]], abs=1e-3)


def test_behind_camera_is_nan_and_dict_round_trip() -> None:
    cam = CAMS[0]
    assert np.all(np.isnan(cam.project([[0.0, 0.0, -1.0]])))
    back = CameraModel.from_dict(cam.to_dict())
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist, cam.dist)


def test_halcon_round_trip_and_kappa_units() -> None:
    cam = CAMS[2]
    h = cam.to_halcon(5e-6)
    f_m = 900.0 * 5e-6
    assert h["Focus"] == pytest.approx(f_m) and h["Kappa"] == pytest.approx(-0.25 / f_m**2)
    back = CameraModel.from_halcon(h)
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist, cam.dist)
    with pytest.raises(CameraModelError):
        CAMS[0].to_halcon(5e-6)


def test_bad_models() -> None:
    with pytest.raises(CameraModelError, match="unknown"):
        CameraModel("fisheye", 640, 480, K, np.zeros(4))  # type: ignore[arg-type]
    with pytest.raises(CameraModelError, match="needs 5"):
        CameraModel("opencv5", 640, 480, K, np.zeros(4))
    with pytest.raises(CameraModelError, match="positive"):
        CameraModel("opencv5", 0, 480, K, np.zeros(5))
