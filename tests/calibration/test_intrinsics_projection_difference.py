"""projection_difference leaves out the pixels a folding lens polynomial cannot unproject (issue 26:
two nearly equal opencv5 cameras of the GoPro set compared 200 px apart there)."""

from __future__ import annotations

import numpy as np

from calibration.camera_model import CameraModel
from calibration.intrinsics import cell_grid, projection_difference


def _wide(fx: float) -> CameraModel:
    """A wide lens under opencv5 whose polynomial folds over before the image corners (as fitted
    to the GoPro 8x6 set: k1 -0.243, k2 0.073, k3 -0.011 at fx ~ 563 px)."""
    K = np.array([[fx, 0.0, 640.0], [0.0, fx, 360.0], [0.0, 0.0, 1.0]])
    return CameraModel("opencv5", 1280, 720, K, np.array([-0.243, 0.073, 0.0, 0.0, -0.011]))


def test_the_same_camera_differs_by_nothing_even_where_its_polynomial_folds() -> None:
    cam = _wide(562.6)
    pts, _, _ = cell_grid(cam.size, 32)
    rays = cam.unproject(pts)
    assert np.nanmax(np.linalg.norm(cam.project(rays) - pts, axis=1)) > 1.0   # some pixels cannot round-trip
    d = projection_difference(cam, cam, pts)
    assert d["rms_px"] < 1e-6
    assert d["points_left_out"] > 0


def test_a_small_focal_change_stays_small() -> None:
    d = projection_difference(_wide(563.6), _wide(562.6))
    assert 0.0 < d["rms_px"] < 2.0
