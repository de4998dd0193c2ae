"""From reflectance to an 8-bit camera image: lighting, lens and sensor defects, encoding.

The pipeline, in the order light meets them (each step off at its default):

1. levels: grey ``black_level + (white_level - black_level) * reflectance`` (linear grey levels,
   DN, of a flat-lit, defect-free camera);
2. ``light_gradient``: brightness ramp from the left to the right edge (uneven light);
3. ``vignetting``: the cos^4 law ``(1 + a rho^2)^-2`` of the distance ``rho`` from the image
   centre (1 at the corners), ``a`` chosen so the corners keep ``1 - vignetting`` of the light;
4. blur: a Gaussian of ``blur_sigma_px`` combined (in quadrature) with defocus, whose sigma
   grows with the distance from the focus plane as a thin lens's blur circle does:
   ``defocus_sigma_px_per_diopter * |1/z - 1/focus_distance_m|`` (``z`` the depth of what the
   pixel sees, camera frame, metres; a diopter is 1/m). Per pixel, by blending the image blurred
   at sigma levels 0.25 px apart (exact where the depth is locally uniform; at depth edges each
   pixel takes its own depth's blur);
5. ``motion_blur_px``: a box blur along a line of that length (px) at ``motion_blur_angle_deg``
   (image frame: 0 is +u, 90 is +v, i.e. down);
6. noise: ``noise_sigma`` (Gaussian, DN) and/or a sensor model: shot noise of a signal of
   ``grey / gain_dn_per_e`` electrons (Poisson below 30 e-, its Gaussian limit of equal mean and
   variance above) plus Gaussian ``read_noise_dn``; variance ``gain * grey + read^2`` (DN^2);
7. ``gamma``: encoding ``255 (grey / 255)^(1 / gamma)``, then rounding and clipping to 0..255;
8. ``jpeg_quality``: JPEG compression at that quality (OpenCV's encoder, 1..100).

Random draws come from the ``rng`` given (OpenCV's generator seeded from it), so a seed gives the
same frames. Our own code where it composes the steps; OpenCV does the filtering and encoding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.errors import DriverInputError

_DEFOCUS_STEP_PX = 0.25
_MAX_SIGMA_PX = 20.0
_DEFOCUS_UNIFORM_PX = 0.05
"""Below this spread of sigma over the image, one blur at the mean sigma (error < 0.025 px)."""
_POISSON_BELOW_E = 30.0


class ImagingError(DriverInputError):
    """An imaging setting is out of its range (the message names it and the range)."""


@dataclass(frozen=True)
class Imaging:
    """How reflectance becomes grey values (DN): levels, lighting, lens and sensor defects."""

    black_level: float = 25.0
    white_level: float = 225.0
    background: float = 0.45
    blur_sigma_px: float = 0.0
    noise_sigma: float = 0.0
    light_gradient: float = 0.0
    """Relative brightness change from the image's left edge to its right edge (uneven light)."""
    vignetting: float = 0.0
    """Fraction of the light lost at the image corners (0: none, 0.4: corners at 60 %)."""
    focus_distance_m: float | None = None
    """Depth (camera z) of the plane in focus; None: no defocus."""
    defocus_sigma_px_per_diopter: float = 0.0
    """Blur sigma (px) per diopter (1/m) of defocus, ``|1/z - 1/focus_distance_m|``."""
    motion_blur_px: float = 0.0
    motion_blur_angle_deg: float = 0.0
    gain_dn_per_e: float = 0.0
    """Grey levels per electron; > 0 turns shot noise on (smaller gain: more electrons, less noise)."""
    read_noise_dn: float = 0.0
    gamma: float = 1.0
    jpeg_quality: int | None = None

    def __post_init__(self) -> None:
        checks = [
            ("vignetting", 0.0 <= self.vignetting < 1.0, "in [0, 1)"),
            ("focus_distance_m", self.focus_distance_m is None or self.focus_distance_m > 0, "> 0 or None"),
            ("defocus_sigma_px_per_diopter", self.defocus_sigma_px_per_diopter >= 0, ">= 0"),
            ("motion_blur_px", self.motion_blur_px >= 0, ">= 0"),
            ("gain_dn_per_e", self.gain_dn_per_e >= 0, ">= 0"),
            ("read_noise_dn", self.read_noise_dn >= 0, ">= 0"),
            ("gamma", self.gamma > 0, "> 0"),
            ("jpeg_quality", self.jpeg_quality is None or 1 <= self.jpeg_quality <= 100, "1..100 or None"),
        ]
        for name, ok, allowed in checks:
            if not ok:
                raise ImagingError(f"imaging.{name} = {getattr(self, name)!r}: must be {allowed}")


def to_grey(reflectance: NDArray[np.float64], imaging: Imaging, rng: np.random.Generator | None = None,
            depth_m: NDArray[np.floating] | None = None) -> NDArray[np.uint8]:
    """Reflectance (H, W) in [0, 1] to an 8-bit image through the steps of the module docstring.

    ``depth_m`` (camera z per pixel, metres; inf for nothing) is needed for defocus only.
    Works in float32 (grey levels need no more).
    """
    from drivers.sim.imaging import kernels as k  # compiled loops, imported on first use

    im = imaging
    refl = np.asarray(reflectance, dtype=np.float64)
    if refl.ndim != 2:
        raise ImagingError(f"reflectance must be an (H, W) array, got shape {refl.shape}")
    h, w = refl.shape
    gain = _NO_GAIN
    if im.vignetting:
        gain = _light_map(w, h, im.vignetting, im.light_gradient)
    elif im.light_gradient:
        ramp = 1.0 + im.light_gradient * (np.arange(w, dtype=np.float32) / max(w - 1, 1) - 0.5)
        gain = ramp[None, :]
    img = np.empty((h, w), dtype=np.float32)
    k.levels(np.ascontiguousarray(refl), float(im.black_level), float(im.white_level - im.black_level),
             np.ascontiguousarray(gain), img)
    img = _blur(img, im, depth_m)
    if im.motion_blur_px > 0:
        img = cv2.filter2D(img, -1, motion_kernel(im.motion_blur_px, im.motion_blur_angle_deg),
                           borderType=cv2.BORDER_REFLECT)
    extra = _NO_GAIN
    if im.noise_sigma > 0 or im.gain_dn_per_e > 0 or im.read_noise_dn > 0:
        rng = rng if rng is not None else np.random.default_rng()
        # OpenCV's generator, seeded from ``rng``: the same frames for the same seed, 5x faster than numpy's.
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        if im.gain_dn_per_e > 0 or im.read_noise_dn > 0:
            img = _add_noise(img, im, rng)
        else:  # Gaussian noise alone: added in the encoding pass below
            extra = np.empty_like(img)
            cv2.randn(extra, 0.0, float(im.noise_sigma))
    if im.gamma != 1.0:
        if extra.size:
            img, extra = img + extra, _NO_GAIN
        np.clip(img, 0, 255, out=img)
        img = cv2.pow(img * np.float32(1 / 255), 1.0 / im.gamma) * np.float32(255)
    out = np.empty((h, w), dtype=np.uint8)
    k.encode(np.ascontiguousarray(img), extra, out)
    if im.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(im.jpeg_quality)])
        if not ok:
            raise ImagingError("JPEG encoding failed (OpenCV built without JPEG support?)")
        decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        if decoded is None:
            raise ImagingError("JPEG decoding failed (OpenCV built without JPEG support?)")
        out = np.asarray(decoded, dtype=np.uint8)
    return out


_NO_GAIN = np.empty((0, 0), dtype=np.float32)


@lru_cache(maxsize=4)
def _vignetting_map(width: int, height: int, vignetting: float) -> NDArray[np.float32]:
    u = (np.arange(width, dtype=np.float64) - (width - 1) / 2) / ((width - 1) / 2)
    v = (np.arange(height, dtype=np.float64) - (height - 1) / 2) / ((height - 1) / 2)
    aspect = (width - 1) / math.hypot(width - 1, height - 1), (height - 1) / math.hypot(width - 1, height - 1)
    rho2 = (u[None, :] * aspect[0]) ** 2 + (v[:, None] * aspect[1]) ** 2  # 1 at the corners
    a = (1.0 - vignetting) ** -0.5 - 1.0
    m = ((1.0 + a * rho2) ** -2).astype(np.float32)
    m.setflags(write=False)
    return m


@lru_cache(maxsize=4)
def _light_map(width: int, height: int, vignetting: float, light_gradient: float) -> NDArray[np.float32]:
    """Vignetting and the light gradient as one gain map (one multiply per frame)."""
    ramp = 1.0 + light_gradient * (np.arange(width, dtype=np.float32) / max(width - 1, 1) - 0.5)
    m = (_vignetting_map(width, height, vignetting) * ramp[None, :]).astype(np.float32)
    m.setflags(write=False)
    return m


def vignetting_factor(width: int, height: int, vignetting: float) -> NDArray[np.float32]:
    """(H, W) relative brightness the vignetting leaves (1 at the centre, 1 - vignetting at corners)."""
    return _vignetting_map(width, height, float(vignetting))


def defocus_sigma_px(imaging: Imaging, depth_m: NDArray[np.floating]) -> NDArray[np.float32]:
    """Total Gaussian blur sigma (px) per pixel: ``blur_sigma_px`` and defocus in quadrature."""
    im = imaging
    base = np.float32(im.blur_sigma_px) ** 2
    if im.focus_distance_m is None or im.defocus_sigma_px_per_diopter == 0:
        return np.full(np.shape(depth_m), np.sqrt(base), dtype=np.float32)
    with np.errstate(divide="ignore"):
        inv = 1.0 / np.asarray(depth_m, dtype=np.float32)  # 0 for background at infinity
    d = np.float32(im.defocus_sigma_px_per_diopter) * np.abs(inv - np.float32(1.0 / im.focus_distance_m))
    out: NDArray[np.float32] = np.sqrt(base + d * d)
    return out


def _blur(img: NDArray[np.float32], im: Imaging, depth_m: NDArray[np.floating] | None) -> NDArray[np.float32]:
    if im.focus_distance_m is None or im.defocus_sigma_px_per_diopter == 0:
        if im.blur_sigma_px > 0:
            return cv2.GaussianBlur(img, (0, 0), im.blur_sigma_px)
        return img
    if depth_m is None:
        raise ImagingError("imaging.focus_distance_m is set but no depth map was given; "
                           "render with drivers.sim.imaging.render_scene to get one")
    lo, hi = _sigma_bounds(im, depth_m)
    if hi - lo < _DEFOCUS_UNIFORM_PX:
        mean = 0.5 * (lo + hi)
        return cv2.GaussianBlur(img, (0, 0), mean) if mean > 1e-3 else img
    sigma = np.minimum(defocus_sigma_px(im, depth_m), np.float32(_MAX_SIGMA_PX))
    n = int(math.ceil((hi - lo) / _DEFOCUS_STEP_PX))
    pos = (sigma - np.float32(lo)) * np.float32(n / (hi - lo))  # 0..n: where between the levels
    out = np.zeros_like(img)
    for i, s in enumerate(np.linspace(lo, hi, n + 1)):
        weight = np.maximum(np.float32(1) - np.abs(pos - np.float32(i)), np.float32(0))
        if np.any(weight):
            out += (cv2.GaussianBlur(img, (0, 0), s) if s > 1e-3 else img) * weight
    return out


def _sigma_bounds(im: Imaging, depth_m: NDArray[np.floating]) -> tuple[float, float]:
    """Bounds (px) on the blur sigma over the image from the depth's range alone (sigma is monotonic
    in the distance from the focus plane in diopters), so the per-pixel map is built only when the
    blur varies; exact for a uniform depth, and never narrower than the map's own range."""
    if im.focus_distance_m is None:
        raise ImagingError("imaging.focus_distance_m is not set: no defocus to bound")
    depth = np.asarray(depth_m)
    inv_lo = 1.0 / float(depth.max())  # 0 when something is at infinity
    inv_hi = 1.0 / float(depth.min()) if float(depth.min()) > 0 else math.inf
    inv_f = 1.0 / im.focus_distance_m
    k, b2 = im.defocus_sigma_px_per_diopter, im.blur_sigma_px**2
    far = max(abs(inv_lo - inv_f), abs(inv_hi - inv_f))
    near = 0.0 if inv_lo <= inv_f <= inv_hi else min(abs(inv_lo - inv_f), abs(inv_hi - inv_f))
    return (min(math.sqrt(b2 + (k * near) ** 2), _MAX_SIGMA_PX), min(math.sqrt(b2 + (k * far) ** 2), _MAX_SIGMA_PX))


def motion_kernel(length_px: float, angle_deg: float) -> NDArray[np.float32]:
    """Normalised kernel of a uniform motion of ``length_px`` along ``angle_deg`` (0: +u, 90: +v).

    The segment is sampled every 1/16 px and splatted bilinearly, so sub-pixel lengths and any
    angle give the right second moment ``length^2 / 12`` along the motion.
    """
    a = math.radians(angle_deg)
    half = int(math.ceil(length_px / 2)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), dtype=np.float64)
    n = max(int(math.ceil(length_px * 16)), 1)
    t = ((np.arange(n) + 0.5) / n - 0.5) * length_px
    x, y = half + t * math.cos(a), half + t * math.sin(a)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), wgt)
    return (k / k.sum()).astype(np.float32)


def _add_noise(img: NDArray[np.float32], im: Imaging, rng: np.random.Generator) -> NDArray[np.float32]:
    """Gaussian ``noise_sigma``, shot noise on the clean signal and read noise (DN)."""
    legacy = None
    if im.noise_sigma > 0:
        legacy = np.empty_like(img)
        cv2.randn(legacy, 0.0, float(im.noise_sigma))
    if im.gain_dn_per_e > 0 or im.read_noise_dn > 0:
        z = np.empty_like(img)
        cv2.randn(z, 0.0, 1.0)
        read2 = np.float32(im.read_noise_dn) ** 2
        if im.gain_dn_per_e > 0:
            from drivers.sim.imaging import kernels as k

            gain = np.float32(im.gain_dn_per_e)
            out = np.empty_like(img)
            below = np.float32(_POISSON_BELOW_E) * gain
            # Shot noise in its Gaussian limit (one compiled pass); a Poisson draw where it is too dark.
            if k.shot_noise(np.ascontiguousarray(img), z, gain, read2, below, out):
                signal = np.maximum(img, np.float32(0))
                low = signal < below
                shot = rng.poisson(signal[low] / gain).astype(np.float32) * gain
                out[low] = shot + z[low] * np.float32(im.read_noise_dn)
        else:
            out = img + z * np.float32(im.read_noise_dn)
        img = out
    return img if legacy is None else img + legacy
