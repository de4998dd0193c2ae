"""Renderer exactness: a rendered mark lands where the camera model projects it (< 0.02 px)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.targets import Chessboard, CircleGrid
from drivers.sim.imaging import PlanarObject, render, render_reflectance, render_scene

K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 480.0], [0.0, 0.0, 1.0]])
MODELS = [
    ("opencv5", [-0.2, 0.1, 0.001, -0.0005, 0.0]),
    ("opencv8", [0.3, -0.1, 0.0005, 0.0002, 0.01, 0.5, -0.05, 0.02]),
    ("division", [-0.25]),
]


@pytest.mark.parametrize(("model", "dist"), MODELS)
def test_disk_centroids_land_on_projected_centres(model: str, dist: list[float]) -> None:
    """Small disks on a plane parallel to the image: their centroid is the projected centre
    (distortion bends a 5 px disk by ~1e-3 px), so the centroid error measures the renderer."""
    cam = CameraModel(model, 1280, 960, K, np.array(dist))  # type: ignore[arg-type]
    grid = CircleGrid(9, 7, 40.0, 5.0)
    T = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, 0.1]), [-0.17, -0.12, 0.5])
    refl = render_reflectance(cam, [PlanarObject(T, grid.reflectance)], background=1.0, supersample=8)
    truth = cam.project(g.transform_points(T, grid.points().xyz_m))
    errors = []
    for u, v in truth:
        u0, v0, h = int(round(u)), int(round(v)), 14
        w = 1.0 - refl[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1]
        vv, uu = np.mgrid[v0 - h : v0 + h + 1, u0 - h : u0 + h + 1]
        errors.append([(w * uu).sum() / w.sum() - u, (w * vv).sum() / w.sum() - v])
    err = np.linalg.norm(errors, axis=1)
    assert err.max() < 0.02, f"max centroid error {err.max():.4f} px"
    assert np.sqrt(np.mean(err**2)) < 0.01


def test_tilted_chessboard_corners_found_where_projected() -> None:
    """OpenCV's corner refinement on a tilted, blurred rendering agrees with the projection."""
    import cv2

    from drivers.sim.imaging import Imaging

    cam = CameraModel("opencv5", 1280, 960, K, np.array([-0.2, 0.1, 0.001, -0.0005, 0.0]))
    board = Chessboard(9, 6, 25.0)
    T = g.make_transform(g.rotvec_to_matrix([0.3, -0.25, 0.1]), [-0.1, -0.06, 0.45])
    img = render(cam, [PlanarObject(T, board.reflectance)], Imaging(blur_sigma_px=0.7))
    truth = cam.project(g.transform_points(T, board.points().xyz_m)).astype(np.float32)
    found = cv2.cornerSubPix(img, truth.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1),
                             (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)).reshape(-1, 2)
    err = np.linalg.norm(found - truth, axis=1)
    # cornerSubPix itself is biased by a few hundredths on tilted, distorted corners.
    assert np.sqrt(np.mean(err**2)) < 0.08


def test_render_is_reproducible_and_noise_has_stated_sigma() -> None:
    from drivers.sim.imaging import Imaging

    cam = CameraModel("opencv5", 320, 240, K / 4 * np.array([[1], [1], [4]]), np.zeros(5))
    flat = [PlanarObject(g.make_transform(np.eye(3), [0, 0, 1.0]), lambda x, y: np.full(x.shape, 0.5))]
    a = render(cam, flat, Imaging(noise_sigma=2.0), np.random.default_rng(1)).astype(float)
    b = render(cam, flat, Imaging(noise_sigma=2.0), np.random.default_rng(1)).astype(float)
    assert np.array_equal(a, b)
    assert 1.8 < a.std() < 2.2
    assert abs(a.mean() - 125.0) < 0.2


@pytest.mark.parametrize(("model", "dist"), MODELS)
def test_ray_field_is_the_exact_lens_inversion(model: str, dist: list[float]) -> None:
    """The interpolated ray field agrees with the per-pixel inversion to < 1e-5 px everywhere."""
    from drivers.sim.imaging import ray_field

    cam = CameraModel(model, 1280, 960, K, np.array(dist))  # type: ignore[arg-type]
    field = ray_field(cam)
    rng = np.random.default_rng(4)
    uv = np.column_stack([rng.integers(0, 1280, 3000), rng.integers(0, 960, 3000)])
    uv = np.vstack([uv, [[0, 0], [1279, 0], [0, 959], [1279, 959]]])
    exact = cam.unproject(uv.astype(float))[:, :2]
    assert np.abs(field[uv[:, 1], uv[:, 0]] - exact).max() * 1400 < 1e-5


def _unbounded(obj: PlanarObject) -> PlanarObject:
    """The same object without its extent (every pixel is tested against the plane)."""
    f = obj.reflectance
    return PlanarObject(obj.T_cam_obj, lambda x, y: f(x, y))


@pytest.mark.parametrize("rotvec", [[0.3, -0.25, 0.1], [1.35, 0.0, 0.2], [0.0, 1.45, -0.3], [0.05, 0.02, 2.0]])
def test_plane_windows_and_depth_order_change_nothing(rotvec: list[float]) -> None:
    """Windows (from the extents) and front-to-back shading give the unbounded render exactly,
    steep and grazing views and an occluding board on a table included, in any object order."""
    dist = np.array([-0.2, 0.1, 0.001, -0.0005, 0.0])
    cam = CameraModel("opencv5", 640, 480, K / 2 * np.array([[1], [1], [2]]), dist)
    board = Chessboard(9, 6, 25.0)
    T = g.make_transform(g.rotvec_to_matrix(rotvec), [-0.1, -0.06, 0.45])
    table = PlanarObject(g.make_transform(g.rotvec_to_matrix(rotvec), [0.0, 0.0, 0.46]),
                         lambda x, y: 0.3 + 0.4 * (np.floor(x / 0.013) % 2))
    objs = [PlanarObject(T, board.reflectance), table]
    assert objs[0].extent_m == board.extent_m()
    fast, depth = render_scene(cam, objs, background=0.45, supersample=4)
    slow, depth2 = render_scene(cam, [_unbounded(o) for o in objs], background=0.45, supersample=4)
    rev, _ = render_scene(cam, objs[::-1], background=0.45, supersample=4)
    assert np.array_equal(fast, slow) and np.array_equal(depth, depth2)
    assert np.array_equal(fast, rev)
    assert 0.2 < np.mean(fast < 0.5) < 0.9  # the board and the table are both seen


def test_depth_is_the_camera_z_of_what_each_pixel_sees() -> None:
    cam = CameraModel("division", 320, 240, K / 4 * np.array([[1], [1], [4]]), np.array([-0.2]))
    R = g.rotvec_to_matrix([0.4, 0.0, 0.0])
    T = g.make_transform(R, [0.0, 0.0, 0.8])
    refl, depth = render_scene(cam, [PlanarObject(T, lambda x, y: np.where(np.abs(x) < 0.2, 0.5, np.nan))])
    rays = cam.unproject(np.column_stack([[160.0, 40.0, 300.0], [120.0, 200.0, 120.0]]))
    n, t = R[:, 2], T[:3, 3]
    lam = (n @ t) / (rays @ n)
    got = depth[[120, 200, 120], [160, 40, 300]]
    hit = np.abs(g.transform_points(g.invert(T), rays * lam[:, None])[:, 0]) < 0.2
    assert np.allclose(got[hit], lam[hit], rtol=1e-12)
    assert np.all(np.isinf(got[~hit])) and np.all(refl[120, 160] == 0.5)


def test_a_reflectance_of_the_wrong_size_is_a_clear_error() -> None:
    from drivers.sim.imaging import RenderError

    cam = CameraModel("opencv5", 64, 48, np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]))
    bad = PlanarObject(g.make_transform(np.eye(3), [0, 0, 1.0]), lambda x, y: np.zeros(3))
    with pytest.raises(RenderError, match="returned 3 values"):
        render_scene(cam, [bad])
