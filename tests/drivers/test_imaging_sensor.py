"""Camera defects of ``drivers.sim.imaging.sensor``: each changes the image the way its model says."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers.sim.imaging import Imaging, ImagingError, defocus_sigma_px, motion_kernel, to_grey

H, W = 240, 320


def flat(level: float = 1.0) -> np.ndarray:
    return np.full((H, W), level)


def test_defaults_are_the_plain_levels() -> None:
    """Nothing on: grey = rint(black + (white - black) * reflectance), no other change."""
    refl = np.random.default_rng(0).random((H, W))
    out = to_grey(refl, Imaging())
    assert np.array_equal(out, np.clip(np.rint(25.0 + 200.0 * refl), 0, 255).astype(np.uint8))


@pytest.mark.parametrize("vignetting", [0.2, 0.5])
def test_vignetting_darkens_corners_by_the_configured_factor(vignetting: float) -> None:
    img = to_grey(flat(1.0), Imaging(black_level=0.0, white_level=250.0, vignetting=vignetting)).astype(float)
    centre = img[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean()
    for corner in (img[0, 0], img[0, -1], img[-1, 0], img[-1, -1]):
        assert corner / centre == pytest.approx(1.0 - vignetting, abs=0.01)
    # Falls monotonically along the diagonal.
    diag = np.array([img[int(t * (H - 1)), int(t * (W - 1))] for t in np.linspace(0.5, 1.0, 12)])
    assert np.all(np.diff(diag) <= 0.5) and diag[0] - diag[-1] > 10


@pytest.mark.parametrize(("gain", "read"), [(0.05, 0.0), (0.2, 1.5), (0.0, 2.0)])
def test_noise_variance_follows_shot_plus_read(gain: float, read: float) -> None:
    """Variance = gain * mean + read^2 (+ 1/12 of the rounding to integers), at several levels."""
    for level in (0.1, 0.5, 0.9):
        im = Imaging(black_level=20.0, white_level=220.0, gain_dn_per_e=gain, read_noise_dn=read)
        img = to_grey(flat(level), im, np.random.default_rng(3)).astype(float)
        mean = 20.0 + 200.0 * level
        assert img.mean() == pytest.approx(mean, abs=0.05)
        assert img.var() == pytest.approx(gain * mean + read**2 + 1 / 12, rel=0.05)


def test_shot_noise_is_poisson_at_low_counts() -> None:
    """At 4 electrons a pixel is a Poisson count times the gain: integer multiples of it."""
    gain = 1.0
    im = Imaging(black_level=4.0, white_level=4.0, gain_dn_per_e=gain)
    img = to_grey(flat(0.5), im, np.random.default_rng(5)).astype(float)
    assert img.mean() == pytest.approx(4.0, abs=0.05)
    assert img.var() == pytest.approx(4.0, rel=0.05)
    assert np.mean(img == 0) == pytest.approx(np.exp(-4.0), abs=0.004)  # P(k = 0) of Poisson(4)


def test_jpeg_is_applied_at_the_quality_given() -> None:
    rng = np.random.default_rng(2)
    refl = cv2.GaussianBlur(rng.random((H, W)), (0, 0), 3.0)
    plain = to_grey(refl, Imaging())
    errors = []
    for q in (95, 60, 20):
        out = to_grey(refl, Imaging(jpeg_quality=q))
        _, buf = cv2.imencode(".jpg", plain, [cv2.IMWRITE_JPEG_QUALITY, q])
        decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        assert decoded is not None and np.array_equal(out, decoded)
        errors.append(np.abs(out.astype(float) - plain).mean())
    assert 0 < errors[0] < errors[1] < errors[2]


def _edge_sigma(img: np.ndarray, row: int) -> float:
    """Blur sigma (px) of the rising step edge at column W/2 on one row: the gradient's spread."""
    g = np.diff(img[row].astype(float))[W // 2 - 20 : W // 2 + 20]
    x = np.arange(g.size)
    m = (g * x).sum() / g.sum()
    return float(np.sqrt(max((g * (x - m) ** 2).sum() / g.sum() - 1 / 12, 0.0)))


def test_defocus_blur_grows_away_from_the_focus_plane() -> None:
    """A step edge seen at several depths: sigma = k |1/z - 1/z_focus|, on both sides of focus."""
    refl = np.zeros((H, W))
    refl[:, W // 2 :] = 1.0
    depths = np.array([0.25, 0.4, 0.5, 0.7, 1.2, np.inf])
    band = H // depths.size
    depth = np.repeat(depths, band)[:, None] * np.ones((1, W))
    im = Imaging(black_level=0.0, white_level=250.0, focus_distance_m=0.5, defocus_sigma_px_per_diopter=1.5)
    img = to_grey(refl, im, depth_m=depth.astype(np.float32))
    # float32 grey before rounding would be exact; 8-bit rounding costs ~0.02 px on these edges.
    for k, z in enumerate(depths):
        expected = 1.5 * abs(1.0 / z - 1.0 / 0.5)
        measured = _edge_sigma(img, k * band + band // 2)
        if expected < 0.3:  # a sharp step: the gradient is one sample wide
            assert measured < 0.35
        else:
            assert measured == pytest.approx(expected, abs=0.08), f"z = {z} m"
    assert defocus_sigma_px(im, np.array([0.5], dtype=np.float32))[0] == 0.0


def test_defocus_needs_a_depth_map() -> None:
    with pytest.raises(ImagingError, match="depth"):
        to_grey(flat(), Imaging(focus_distance_m=0.5, defocus_sigma_px_per_diopter=1.0))


@pytest.mark.parametrize(("length", "angle"), [(7.0, 30.0), (4.5, 90.0), (0.6, 0.0)])
def test_motion_blur_spreads_a_point_along_the_motion(length: float, angle: float) -> None:
    k = motion_kernel(length, angle).astype(float)
    assert k.sum() == pytest.approx(1.0)
    yy, xx = np.mgrid[: k.shape[0], : k.shape[1]]
    cx, cy = (k * xx).sum(), (k * yy).sum()
    assert (cx, cy) == pytest.approx(((k.shape[1] - 1) / 2, (k.shape[0] - 1) / 2), abs=1e-6)
    a = np.radians(angle)
    along = (xx - cx) * np.cos(a) + (yy - cy) * np.sin(a)
    across = -(xx - cx) * np.sin(a) + (yy - cy) * np.cos(a)
    # A uniform segment has variance L^2/12 along; the bilinear splat adds under 1/4 px^2.
    assert length**2 / 12 <= (k * along**2).sum() <= length**2 / 12 + 0.25
    assert (k * across**2).sum() <= 0.25
    # And in an image: a lone bright pixel becomes that kernel.
    refl = np.zeros((H, W))
    refl[H // 2, W // 2] = 1.0
    img = to_grey(refl, Imaging(black_level=0.0, white_level=255.0, motion_blur_px=length,
                                motion_blur_angle_deg=angle)).astype(float)
    r, c = k.shape[0] // 2, k.shape[1] // 2
    patch = img[H // 2 - r : H // 2 + r + 1, W // 2 - c : W // 2 + c + 1]
    assert np.abs(patch - 255.0 * k).max() <= 0.5 + 1e-3
    assert img.sum() == pytest.approx(patch.sum())


@pytest.mark.parametrize("gamma", [0.5, 1.8, 2.2])
def test_gamma_maps_grey_levels(gamma: float) -> None:
    levels = np.linspace(0.0, 1.0, 11)
    refl = np.repeat(levels, W // 11 + 1)[:W][None, :] * np.ones((H, 1))
    out = to_grey(refl, Imaging(black_level=0.0, white_level=255.0, gamma=gamma))
    linear = 255.0 * refl[0]
    assert np.array_equal(out[0], np.rint(255.0 * (linear / 255.0) ** (1.0 / gamma)).astype(np.uint8))


def test_every_defect_is_deterministic_per_seed() -> None:
    im = Imaging(vignetting=0.3, blur_sigma_px=0.5, focus_distance_m=0.4, defocus_sigma_px_per_diopter=1.0,
                 motion_blur_px=1.5, motion_blur_angle_deg=20, gain_dn_per_e=0.05, read_noise_dn=1.0,
                 noise_sigma=0.5, gamma=2.2, jpeg_quality=85)
    refl = np.random.default_rng(0).random((H, W))
    depth = np.linspace(0.3, 0.9, H)[:, None] * np.ones((1, W))
    a = to_grey(refl, im, np.random.default_rng(11), depth)
    b = to_grey(refl, im, np.random.default_rng(11), depth)
    c = to_grey(refl, im, np.random.default_rng(12), depth)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize(("field", "value"), [("vignetting", 1.0), ("gamma", 0.0), ("jpeg_quality", 0),
                                               ("gain_dn_per_e", -1.0), ("focus_distance_m", -0.5)])
def test_out_of_range_settings_are_refused_by_name(field: str, value: float) -> None:
    with pytest.raises(ImagingError, match=field):
        Imaging(**{field: value})  # type: ignore[arg-type]


def test_defocus_follows_the_rendered_depth_of_a_tilted_plane() -> None:
    """End to end: a striped plane tilted away from the camera, focused at its near (top) edge, is
    sharp there and blurred where it is farther, by the sigma its rendered depth gives."""
    from calibration import geometry as g
    from calibration.camera_model import CameraModel
    from drivers.sim.imaging import PlanarObject, render_scene

    cam = CameraModel("opencv5", W, H, np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]]), np.zeros(5))
    T = g.make_transform(g.rotvec_to_matrix([0.9, 0.0, 0.0]), [0.0, 0.0, 0.6])
    stripes = PlanarObject(T, lambda x, y: (np.floor(x / 0.08) % 2).astype(np.float64))
    refl, depth = render_scene(cam, [stripes], supersample=6)
    z_top, z_bottom = float(np.median(depth[10])), float(np.median(depth[-10]))
    assert z_bottom > 1.5 * z_top  # the plane recedes downwards
    im = Imaging(black_level=0.0, white_level=250.0, focus_distance_m=z_top, defocus_sigma_px_per_diopter=1.5)
    img = to_grey(refl, im, depth_m=depth).astype(float)
    sharp = to_grey(refl, Imaging(black_level=0.0, white_level=250.0)).astype(float)

    def contrast(a: np.ndarray, row: int) -> float:
        return float(np.abs(np.diff(a[row - 3 : row + 4], axis=1)).max())

    assert contrast(img, 10) == pytest.approx(contrast(sharp, 10), rel=0.1)  # in focus: as sharp as no defocus
    expected = 1.5 * abs(1 / z_bottom - 1 / z_top)
    assert expected > 1.0
    # A step blurred by sigma has a peak gradient of 250 / (sigma sqrt(2 pi)) per pixel.
    assert contrast(img, H - 10) == pytest.approx(250 / (expected * np.sqrt(2 * np.pi)), rel=0.15)


@pytest.mark.parametrize("focus_m", [0.3, 0.5, 2.0])
def test_the_blur_range_from_the_depth_range_is_the_per_pixel_range(focus_m: float) -> None:
    from drivers.sim.imaging.sensor import _sigma_bounds

    rng = np.random.default_rng(8)
    im = Imaging(blur_sigma_px=0.4, focus_distance_m=focus_m, defocus_sigma_px_per_diopter=1.3)
    for depth in (rng.uniform(0.35, 0.9, (40, 50)), np.full((40, 50), 0.6), np.where(rng.random((40, 50)) < 0.1,
                                                                                          np.inf, 0.45)):
        sigma = defocus_sigma_px(im, depth.astype(np.float32))
        lo, hi = _sigma_bounds(im, depth)
        assert lo <= float(sigma.min()) + 1e-5 and hi >= float(sigma.max()) - 1e-5
    flat = np.full((40, 50), 0.6)
    lo, hi = _sigma_bounds(im, flat)
    assert lo == pytest.approx(hi) == pytest.approx(float(defocus_sigma_px(im, flat.astype(np.float32))[0, 0]))
