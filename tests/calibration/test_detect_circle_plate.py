"""Our circle plate detector on rendered plates: ids follow the plate, sub-pixel centres, rejections."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.detect import circle_centre_bias_px, detect
from calibration.detect.circle_plate import perspective_bias
from calibration.geometry import make_transform, rotvec_to_matrix, transform_points
from calibration.targets import CirclePlate
from drivers.sim.imaging import Imaging, PlanarObject, render
from tests.calibration.conftest import plate_pose, render_target, truth_uv

PLATE = CirclePlate(7, 7, 12.5, 6.25)


@pytest.mark.parametrize("tilt_deg, roll_deg", [(0, 0), (45, 90), (30, 180), (40, 270), (20, 135)])
def test_rendered_plate_ids_and_centres(camera: CameraModel, tilt_deg: float, roll_deg: float) -> None:
    T = plate_pose(PLATE, 0.25, tilt_deg, tilt_dir_deg=30, roll_deg=roll_deg)
    img = render_target(camera, PLATE, T, noise=1.0, blur=0.7, seed=int(roll_deg))
    det = detect(img, PLATE, "r.png")
    assert det.found, det.reason
    assert det.ids.tolist() == list(range(49))
    truth = truth_uv(camera, PLATE, T)
    err = np.hypot(*(det.uv - truth[det.ids]).T)
    assert err.max() < 0.06
    # raw ellipse centres carry the perspective bias; the corrected ones do not
    bias = circle_centre_bias_px(camera, T, PLATE.points().xyz_m, PLATE.radius_m)
    assert det.uv_ellipse is not None
    ell_err = np.hypot(*(det.uv_ellipse - (truth + bias)[det.ids]).T)
    assert np.sqrt(np.mean(ell_err**2)) < 0.03
    if tilt_deg >= 40:
        assert np.sqrt(np.mean(np.sum(bias**2, axis=1))) > 0.03  # the bias is real at this tilt ...
        assert np.sqrt(np.mean(err**2)) < 0.5 * np.sqrt(np.mean(np.sum(bias**2, axis=1)))  # ... and removed
    assert set(det.quality) == {"edge_contrast_grey", "blur_sigma_px", "coverage_fraction"}
    assert 0.05 < det.quality["coverage_fraction"] < 0.9


def test_mirrored_view_ids_follow_the_plate(camera: CameraModel) -> None:
    plate = CirclePlate(7, 5, 15.0, 7.5)
    T = plate_pose(plate, 0.3, 25, tilt_dir_deg=60, roll_deg=30)
    img = render_target(camera, plate, T, seed=3)[:, ::-1].copy()
    det = detect(img, plate)
    assert det.found, det.reason
    truth = truth_uv(camera, plate, T)
    truth[:, 0] = camera.width - 1 - truth[:, 0]
    assert np.hypot(*(det.uv - truth[det.ids]).T).max() < 0.06


def test_occluded_marks_are_left_out_the_rest_found(camera: CameraModel) -> None:
    T = plate_pose(PLATE, 0.25, 20, roll_deg=10)
    truth = truth_uv(camera, PLATE, T)
    img = render_target(camera, PLATE, T, seed=5)
    for k in (10, 24):  # white patches hide two marks completely, a grey one half of a third
        u, v = np.rint(truth[k]).astype(int)
        img[v - 14 : v + 15, u - 14 : u + 15] = 225
    u, v = np.rint(truth[40]).astype(int)
    img[v - 14 : v + 15, u : u + 15] = 128
    det = detect(img, PLATE)
    assert det.found, det.reason
    assert 10 not in det.ids and 24 not in det.ids and 40 not in det.ids
    assert len(det.ids) == 46
    assert np.hypot(*(det.uv - truth[det.ids]).T).max() < 0.06


def test_uneven_light_and_clutter(camera: CameraModel) -> None:
    T = plate_pose(PLATE, 0.32, 35, tilt_dir_deg=200, roll_deg=-20, shift_m=(0.02, 0.01))
    R = rotvec_to_matrix([0.1, -0.2, 0.3])
    clutter = PlanarObject(make_transform(R, [-0.12, -0.09, 0.6]),
                           lambda x, y: np.where((np.floor(x / 0.01) + np.floor(y / 0.013)) % 2 == 0, 0.1, 0.9))
    img = render(camera, [PlanarObject(T, PLATE.reflectance), clutter],
                 Imaging(noise_sigma=2.0, blur_sigma_px=1.0, light_gradient=0.6), np.random.default_rng(7),
                 supersample=4)
    det = detect(img, PLATE)
    assert det.found, det.reason
    assert len(det.ids) == 49
    assert np.hypot(*(det.uv - truth_uv(camera, PLATE, T)[det.ids]).T).max() < 0.1


def test_missing_triangle_is_rejected(camera: CameraModel) -> None:
    p = PLATE.pitch_m

    def no_triangle(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = PLATE.reflectance(x, y)
        tri = (x > -p) & (y > -p) & ((x + p) + (y + p) <= p / 2 + 1e-9)
        return np.where(tri, 1.0, r)

    T = plate_pose(PLATE, 0.25, 20, roll_deg=30)
    img = render(camera, [PlanarObject(T, no_triangle)], Imaging(noise_sigma=1.0, blur_sigma_px=0.7),
                 np.random.default_rng(1), supersample=4)
    det = detect(img, PLATE)
    assert not det.found
    assert "orientation unreadable" in det.reason


@pytest.mark.parametrize("printed", [CirclePlate(7, 6, 12.5, 6.25), CirclePlate(8, 7, 12.5, 6.25)])
def test_wrong_mark_count_is_rejected(camera: CameraModel, printed: CirclePlate) -> None:
    T = plate_pose(printed, 0.25, 15, roll_deg=5)
    det = detect(render_target(camera, printed, T, seed=2), PLATE)
    assert not det.found
    assert "mark count mismatch" in det.reason


def test_cropped_plate_has_no_frame(camera: CameraModel) -> None:
    T = plate_pose(PLATE, 0.2, 10, shift_m=(0.06, 0.0))
    det = detect(render_target(camera, PLATE, T), PLATE)
    assert not det.found
    assert "no frame" in det.reason


def test_perspective_bias_matches_the_conic_model_without_a_camera() -> None:
    """With a distortion-free camera the local-homography bias equals the known-pose bias."""
    cam = CameraModel("opencv5", 1280, 960, np.array([[1500.0, 0, 640], [0, 1500.0, 480], [0, 0, 1]]))
    T = plate_pose(PLATE, 0.25, 50, tilt_dir_deg=20)
    xyz = PLATE.points().xyz_m
    uv = cam.project(transform_points(T, xyz))
    expected = circle_centre_bias_px(cam, T, xyz, PLATE.radius_m)
    got = perspective_bias(xyz[:, :2] / PLATE.pitch_m, uv, PLATE.radius_m / PLATE.pitch_m)
    assert np.abs(expected).max() > 0.05
    assert np.abs(got - expected).max() < 1e-6
