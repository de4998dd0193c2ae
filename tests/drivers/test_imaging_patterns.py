"""The compiled target patterns and the threaded renderer give the numpy path's bytes exactly."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.targets import Charuco, Chessboard, CircleGrid, CirclePlate
from drivers.sim.imaging import PlanarObject, render_scene
from drivers.sim.imaging import renderer as render
from drivers.sim.imaging.patterns import shade_hits, shader_for

K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 480.0], [0.0, 0.0, 1.0]])
TARGETS = [
    CirclePlate(7, 7, 20.0, 10.0),
    CirclePlate(5, 4, 12.5, 6.25),
    Chessboard(9, 6, 25.0),
    CircleGrid(9, 7, 40.0, 5.0),
    CircleGrid(4, 11, 20.0, 10.0, asymmetric=True),
]


def _edge_points(target: CirclePlate | Chessboard | CircleGrid) -> tuple[np.ndarray, np.ndarray]:
    """Points exactly on (and one ulp beside) the pattern's edges: where a different rounding
    or operation order would flip the value."""
    x0, y0, x1, y1 = target.extent_m()
    xs = [x0, x1]
    ys = [y0, y1]
    if isinstance(target, CirclePlate):
        p = target.pitch_m
        fx0, fy0, fx1, fy1 = target.frame_inner_m()
        xs += [fx0, fx1, fx0 - p / 2, fx1 + p / 2, fx0 + p / 2]
        ys += [fy0, fy1, fy0 - p / 2, fy1 + p / 2, fy0 + p / 2]
        rim = target.points().xyz_m[:, :2] + [target.radius_m, 0.0]
        xs += list(rim[:, 0])
        ys += list(rim[:, 1])
    elif isinstance(target, Chessboard):
        s = target.square_m
        xs += [i * s for i in range(-2, target.cols + 2)]
        ys += [j * s for j in range(-2, target.rows + 2)]
    else:
        rim = target.points().xyz_m[:, :2] + [target.diameter_mm * 1e-3 / 2, 0.0]
        xs += list(rim[:, 0])
        ys += list(rim[:, 1])
    gx, gy = np.meshgrid(np.array(xs), np.array(ys))
    x, y = gx.ravel(), gy.ravel()
    return (np.concatenate([x, np.nextafter(x, np.inf), np.nextafter(x, -np.inf), x, x]),
            np.concatenate([y, y, y, np.nextafter(y, np.inf), np.nextafter(y, -np.inf)]))


@pytest.mark.parametrize("target", TARGETS, ids=lambda t: t.describe())
def test_compiled_pattern_is_the_numpy_reflectance_bit_for_bit(target: CirclePlate | Chessboard | CircleGrid) -> None:
    shader = shader_for(target.reflectance)
    assert shader is not None
    x0, y0, x1, y1 = target.extent_m()
    rng = np.random.default_rng(3)
    rx = rng.uniform(x0 - 0.02, x1 + 0.02, 200_000)
    ry = rng.uniform(y0 - 0.02, y1 + 0.02, 200_000)
    ex, ey = _edge_points(target)
    x, y = np.concatenate([rx, ex]), np.concatenate([ry, ey])
    expected = target.reflectance(x, y)
    n = x.size
    value = np.full(n, -1.0)
    depth = np.full(n, np.inf)
    which = np.full(n, -1, dtype=np.int32)
    shade_hits(shader.kind, shader.g, shader.centres, shader.cols, shader.rows, n, x, y, np.full(n, 0.5),
               np.arange(n, dtype=np.int64), 3, value, depth, which)
    defined = np.isfinite(expected)
    assert np.array_equal(value[defined], expected[defined])
    assert np.all(value[~defined] == -1.0) and np.all(which[~defined] == -1)  # NaN: the object is not there
    assert np.all(which[defined] == 3) and np.all(depth[defined] == 0.5)
    assert 0.01 < np.mean(expected[defined] == 0.0) < 0.99  # both black and white were tested


def test_only_the_targets_own_methods_are_compiled() -> None:
    plate = CirclePlate(7, 7, 20.0, 10.0)

    class Painted(CirclePlate):
        def reflectance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
            return np.full(x.shape, 0.5)

    assert shader_for(plate.reflectance) is not None
    assert shader_for(lambda x, y: plate.reflectance(x, y)) is None
    assert shader_for(Painted(7, 7, 20.0, 10.0).reflectance) is None
    assert shader_for(Charuco(8, 6, 30.0, 22.0, "DICT_5X5_100").reflectance) is None


def _wrapped(obj: PlanarObject) -> PlanarObject:
    """The same object through a plain function: the renderer's numpy path."""
    f = obj.reflectance
    return PlanarObject(obj.T_cam_obj, lambda x, y: f(x, y), obj.extent_m)


@pytest.mark.parametrize("supersample", [1, 4, 6, 8])
def test_frames_with_compiled_patterns_equal_the_numpy_path(supersample: int) -> None:
    """A scene of every compiled pattern, overlapping, on a table, through a distorted lens."""
    cam = CameraModel("opencv5", 640, 480, K / 2 * np.array([[1], [1], [2]]), np.array([-0.2, 0.1, 0.001, 0, 0]))
    R = g.rotvec_to_matrix([0.35, -0.3, 0.1])
    objs = [
        PlanarObject(g.make_transform(R, [-0.12, -0.08, 0.45]), CirclePlate(7, 7, 20.0, 10.0).reflectance),
        PlanarObject(g.make_transform(R, [0.0, -0.02, 0.5]), Chessboard(9, 6, 25.0).reflectance),
        PlanarObject(g.make_transform(g.rotvec_to_matrix([0, 0, 0.3]), [-0.05, 0.02, 0.55]),
                     CircleGrid(4, 11, 20.0, 10.0, asymmetric=True).reflectance),
        PlanarObject(g.make_transform(R, [0.0, 0.0, 0.6]), lambda x, y: 0.3 + 0.4 * (np.floor(x / 0.013) % 2)),
    ]
    fast, depth = render_scene(cam, objs, 0.45, supersample)
    slow, depth2 = render_scene(cam, [_wrapped(o) for o in objs], 0.45, supersample)
    assert np.array_equal(fast, slow) and np.array_equal(depth, depth2)
    plain = [0.0, 1.0, 0.3, 0.3 + 0.4]
    for value in plain:
        assert np.any(fast == value)  # the patterns and the table are in view
    assert np.sum(depth < 0.5) > 10_000 and np.sum(depth > 0.55) > 10_000  # near and far planes
    if supersample > 1:
        assert np.sum(~np.isin(fast, plain)) > 1000  # anti-aliased edges


def test_the_image_does_not_depend_on_the_thread_count(monkeypatch: pytest.MonkeyPatch) -> None:
    cam = CameraModel("division", 1280, 960, K, np.array([-0.25]))
    T = g.make_transform(g.rotvec_to_matrix([0.2, 0.3, 0.1]), [-0.1, -0.1, 0.5])
    objs = [PlanarObject(T, CirclePlate(7, 7, 20.0, 10.0).reflectance),
            PlanarObject(g.make_transform(np.eye(3), [0, 0, 0.6]), lambda x, y: np.where(x > 0, 0.2, 0.8))]
    frames = []
    for threads in (1, 2, 3):
        monkeypatch.setattr(render, "RENDER_THREADS", threads)
        frames.append(render_scene(cam, objs, 0.45, 6))
    for value, depth in frames[1:]:
        assert np.array_equal(value, frames[0][0]) and np.array_equal(depth, frames[0][1])


def test_an_error_in_a_render_thread_reaches_the_caller(monkeypatch: pytest.MonkeyPatch) -> None:
    """A reflectance that breaks the contract in a band shaded by a pool worker is the caller's
    typed error, and the pool is still usable after it."""
    from drivers.sim.imaging import RenderError

    monkeypatch.setattr(render, "RENDER_THREADS", 2)
    cam = CameraModel("opencv5", 640, 480, K / 2 * np.array([[1], [1], [2]]))
    T = g.make_transform(np.eye(3), [0, 0, 1.0])
    bad = PlanarObject(T, lambda x, y: np.zeros(3) if np.any(y > 0.05) else np.zeros(x.shape))
    with pytest.raises(RenderError, match="returned 3 values"):
        render_scene(cam, [bad])
    value, _ = render_scene(cam, [PlanarObject(T, lambda x, y: np.full(x.shape, 0.25))])
    assert np.all(value == 0.25)


@pytest.mark.parametrize("supersample", [1, 4])
def test_rays_parallel_to_a_pattern_miss_it(supersample: int) -> None:
    """Rays with ``w = n . ray == 0`` exactly (parallel to the plane) are no hit, and no error:
    a field of all-zero rays against a plane whose normal is the camera's x axis."""
    from drivers.sim.imaging.patterns import supersample_alone

    shader = shader_for(CirclePlate(7, 7, 20.0, 10.0).reflectance)
    assert shader is not None
    field = np.zeros((3, 4, 2))
    H = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # row 2: the normal (1, 0, 0)
    value, depth, which = np.full(12, 0.45), np.full(12, np.inf), np.full(12, -1, dtype=np.int32)
    shader.shade_pixels(field, 0, 3, 0, 4, H, 0.1, 0, value, depth, which)
    assert np.all(value == 0.45) and np.all(np.isinf(depth)) and np.all(which == -1)
    out = np.empty(2)
    supersample_alone(shader.kind, shader.g, shader.centres, shader.cols, shader.rows, field,
                      np.array([1, 2]), np.array([1, 3]), supersample, H, 0.1, 0.45, out)
    assert np.all(out == 0.45)
