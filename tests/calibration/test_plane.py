"""Image points to the plane and back."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, look_at
from calibration.measure import PlaneError, image_to_plane, plane_to_image

CAM = CameraModel("opencv5", 1280, 960, np.array([[1100.0, 0, 640], [0, 1100, 480], [0, 0, 1]]),
                  np.array([-0.2, 0.05, 0.001, 0.0, 0.0]))


def test_round_trip_on_tilted_plane() -> None:
    T = invert(look_at([0.2, -0.3, -0.6], [0.1, 0.05, 0.0], up=[0, -1, 0]))
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.05, 0.25, (30, 2))
    uv = plane_to_image(CAM, T, xy)
    back = image_to_plane(CAM, T, uv)
    assert np.allclose(back[:, :2], xy, atol=1e-9)
    assert np.all(back[:, 2] == 0.0)


def test_ray_missing_the_plane() -> None:
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]   # plane containing the optical axis, tilted
    T[:3, 3] = [0, 0.1, 1.0]
    with pytest.raises(PlaneError, match="does not meet the plane"):
        image_to_plane(CAM, T, [[640.0, 100.0]])


def test_invalid_pose() -> None:
    with pytest.raises(ValueError, match="T_cam_plane"):
        image_to_plane(CAM, np.zeros((4, 4)), [[1.0, 2.0]])
