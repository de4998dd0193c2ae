"""The OpenCV camera models against OpenCV itself: ``CameraModel.project`` equals ``cv2.projectPoints``.

For ``opencv5`` (k1, k2, p1, p2, k3) and ``opencv8`` (the rational model, k1..k6) our own
distortion code must give exactly OpenCV's pixels for the same ``K`` and ``dist``, over the whole
image and with strong, real-lens coefficients (the Udacity car camera's, the GoPro's and mrcal's
fisheye calibration in OpenCV's rational model), and undistorting must invert it as OpenCV's
iterative ``undistortPointsIter`` does. OpenCV has no division model, so it is not compared here.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform, rotvec_to_matrix

F64 = NDArray[np.float64]

# (model, width, height, fx, fy, cx, cy, dist): measured on real lenses (tests/data/*/SOURCE.txt).
LENSES = {
    "udacity car camera, opencv5": ("opencv5", 1280, 720, 1156.457, 1151.267, 671.319, 389.217,
                                    [-0.24667, -0.02544, -0.00067, 0.00013, 0.01067]),
    "gopro wide, opencv5": ("opencv5", 1280, 960, 560.035, 561.094, 651.084, 498.914,
                            [-0.23260, 0.06155, -0.00003, 0.00006, -0.00752]),
    "synthetic tangential-heavy, opencv5": ("opencv5", 1280, 960, 1400.0, 1395.0, 650.0, 470.0,
                                            [0.12, -0.35, 0.004, -0.003, 0.25]),
    "mrcal samyang fisheye, opencv8": ("opencv8", 6016, 4016, 2073.873, 2077.452, 3004.687, 1997.377,
                                       [0.479161, 0.026682, 0.000044, -0.000012, 0.000090, 0.766691, 0.096336,
                                        0.001408]),
    "synthetic rational, opencv8": ("opencv8", 1280, 960, 1050.0, 1052.0, 641.0, 479.0,
                                    [-0.3, 0.12, 0.001, -0.0015, -0.02, 0.05, 0.01, 0.002]),
}


def _camera(name: str) -> CameraModel:
    model, w, h, fx, fy, cx, cy, dist = LENSES[name]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraModel(model, w, h, K, np.array(dist, dtype=np.float64))  # type: ignore[arg-type]


def _rays_over_the_image(camera: CameraModel, n: int = 25, extent: float = 1.0) -> F64:
    """Camera-frame points (m) at 0.3 to 3 m whose *ideal* (pinhole) images span ``extent`` of the sensor.

    Built from the pinhole model, not from our own unproject, so the test does not lean on the
    code under test; beyond the data a polynomial lens model may fold back on itself, so the
    inverse is only checked inside ``extent`` < 1.
    """
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, n), np.linspace(0, camera.height - 1, n))
    x = (u.ravel() - cx) / fx * extent
    y = (v.ravel() - cy) / fy * extent
    depth = np.linspace(0.3, 3.0, x.size)
    return np.column_stack([x * depth, y * depth, depth])


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_project_equals_cv2_project_points_over_the_image(lens: str) -> None:
    camera = _camera(lens)
    points = _rays_over_the_image(camera)
    ours = camera.project(points)
    theirs, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist)
    theirs = theirs.reshape(-1, 2)
    assert np.isfinite(ours).all()
    assert np.abs(ours - theirs).max() < 1e-6  # px: the same formula, to rounding
    assert np.ptp(ours[:, 0]) > 0.5 * camera.width and np.ptp(ours[:, 1]) > 0.5 * camera.height


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_project_equals_cv2_for_a_posed_target(lens: str) -> None:
    """A plate at a pose (``T_cam_target``): our transform + project equals projectPoints with rvec/tvec."""
    camera = _camera(lens)
    rng = np.random.default_rng(7)
    rvec = np.array([0.35, -0.5, 0.2])
    tvec = np.array([0.05, -0.03, 0.6])
    T_cam_target = make_transform(rotvec_to_matrix(rvec), tvec)
    obj = np.column_stack([rng.uniform(-0.2, 0.2, 200), rng.uniform(-0.15, 0.15, 200), np.zeros(200)])
    in_cam = obj @ T_cam_target[:3, :3].T + T_cam_target[:3, 3]
    ours = camera.project(in_cam)
    theirs, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)
    assert np.abs(ours - theirs.reshape(-1, 2)).max() < 1e-6


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_undistort_inverts_projection_like_opencvs_iterative_undistort(lens: str) -> None:
    camera = _camera(lens)
    points = _rays_over_the_image(camera, n=15, extent=0.7)
    uv = camera.project(points)
    truth = points[:, :2] / points[:, 2:3]
    ours = camera.unproject(uv)[:, :2]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    theirs = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), camera.K, camera.dist, None, None, criteria).reshape(-1, 2)
    f = float(camera.K[0, 0])
    assert np.abs(ours - truth).max() * f < 1e-4  # px: ours inverts its own projection exactly
    # OpenCV's fixed-point iteration agrees where it converges (it may not in the fisheye's far corners)
    converged = np.abs(theirs - truth).max(axis=1) * f < 1e-3
    assert converged.mean() > 0.5
    assert np.abs(ours[converged] - theirs[converged]).max() * f < 1e-3


def test_the_comparison_sees_a_wrong_coefficient() -> None:
    """The check is sensitive: a tenth of a percent change of k1 shows up as pixels in OpenCV's answer."""
    camera = _camera("udacity car camera, opencv5")
    points = _rays_over_the_image(camera)
    dist = camera.dist.copy()
    dist[0] *= 1.001
    theirs, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, dist)
    assert np.abs(camera.project(points) - theirs.reshape(-1, 2)).max() > 0.05
