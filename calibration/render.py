"""Geometrically exact rendering of planar patterns seen by a camera model.

Inverse mapping: every pixel's ray (through the full lens model) is intersected with each
planar object, and the object's reflectance function is evaluated at the hit point in the
object's own frame. Pixels whose neighbourhood is not uniform are supersampled on an
``n x n`` grid (box filter over the pixel's area), so edges are anti-aliased and land where the
model projects them. Sub-pixel rays are interpolated linearly from the per-pixel ray field
(the field is smooth; the interpolation error is ~1e-9 px), which keeps the cost at one
lens inversion per pixel, cached per camera model.

This is our own code: OpenCV has no renderer; the virtual cell and the benchmarks need one whose
geometry is known to better than 0.02 px.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel

Reflectance = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


@dataclass(frozen=True)
class PlanarObject:
    """A plane ``z = 0`` of frame ``obj`` placed at ``T_cam_obj``, with its printed pattern."""

    T_cam_obj: NDArray[np.float64]
    reflectance: Reflectance


@dataclass(frozen=True)
class Imaging:
    """How reflectance becomes grey values: levels, lighting, blur (px) and noise (grey levels)."""

    black_level: float = 25.0
    white_level: float = 225.0
    background: float = 0.45
    blur_sigma_px: float = 0.0
    noise_sigma: float = 0.0
    light_gradient: float = 0.0
    """Relative brightness change from the image's left edge to its right edge (uneven light)."""


def ray_field(camera: CameraModel) -> NDArray[np.float64]:
    """(H, W, 2) normalized ideal ray coordinates ``(x, y)`` (ray ``[x, y, 1]``) per pixel centre."""
    return _ray_field_cached(camera.model, camera.width, camera.height,
                             camera.K.tobytes(), camera.dist.tobytes())


@lru_cache(maxsize=8)
def _ray_field_cached(model: str, width: int, height: int, K: bytes, dist: bytes) -> NDArray[np.float64]:
    cam = CameraModel(model, width, height,  # type: ignore[arg-type]
                      np.frombuffer(K).reshape(3, 3).copy(), np.frombuffer(dist).copy())
    uu, vv = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = cam.unproject(np.column_stack([uu.ravel(), vv.ravel()]))[:, :2]
    field = rays.reshape(height, width, 2)
    field.setflags(write=False)
    return field


def _hit(rays_xy: NDArray[np.float64], T_cam_obj: NDArray[np.float64]
         ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Intersect rays ``[x, y, 1]`` with the object's plane: object-frame x, y and depth."""
    R = T_cam_obj[:3, :3]
    t = T_cam_obj[:3, 3]
    n = R[:, 2]
    denom = rays_xy[..., 0] * n[0] + rays_xy[..., 1] * n[1] + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(n @ t) / denom
    px = lam * rays_xy[..., 0] - t[0]
    py = lam * rays_xy[..., 1] - t[1]
    pz = lam - t[2]
    ox = R[0, 0] * px + R[1, 0] * py + R[2, 0] * pz
    oy = R[0, 1] * px + R[1, 1] * py + R[2, 1] * pz
    return ox, oy, lam


def _shade(rays_xy: NDArray[np.float64], objects: Sequence[PlanarObject], background: float
           ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Reflectance and the index of the visible object (-1: background) for each ray."""
    shape = rays_xy.shape[:-1]
    value = np.full(shape, background)
    depth = np.full(shape, np.inf)
    which = np.full(shape, -1, dtype=np.int64)
    for k, obj in enumerate(objects):
        ox, oy, lam = _hit(rays_xy, obj.T_cam_obj)
        ok = np.isfinite(lam) & (lam > 0) & (lam < depth)
        if not np.any(ok):
            continue
        r = np.full(shape, np.nan)
        r[ok] = obj.reflectance(ox[ok], oy[ok])
        vis = ok & np.isfinite(r)
        value[vis] = r[vis]
        depth[vis] = lam[vis]
        which[vis] = k
    return value, which


def render_reflectance(camera: CameraModel, objects: Sequence[PlanarObject], background: float = 0.45,
                       supersample: int = 8) -> NDArray[np.float64]:
    """(H, W) mean reflectance over each pixel's area (box filter), in [0, 1]."""
    field = ray_field(camera)
    value: NDArray[np.float64]
    value, which = _shade(field, objects, background)
    # A pixel needs supersampling when any 8-neighbour saw something else.
    v8 = np.round(value * 1e6).astype(np.int64) * 64 + which
    edge = np.zeros(v8.shape, dtype=bool)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            if du or dv:
                edge |= v8 != np.roll(np.roll(v8, dv, axis=0), du, axis=1)
    rows, cols = np.nonzero(edge)
    if rows.size == 0 or supersample <= 1:
        return value
    # Local ray derivatives per pixel (central differences of the smooth ray field).
    d_du = np.gradient(field, axis=1)
    d_dv = np.gradient(field, axis=0)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid_u, grid_v = np.meshgrid(offsets, offsets)
    ou, ov = grid_u.ravel(), grid_v.ravel()
    base = field[rows, cols]
    sub = (base[:, None, :] + ou[None, :, None] * d_du[rows, cols][:, None, :]
           + ov[None, :, None] * d_dv[rows, cols][:, None, :])
    sub_value, _ = _shade(sub, objects, background)
    out = value.copy()
    out[rows, cols] = sub_value.mean(axis=1)
    return out


def to_grey(reflectance: NDArray[np.float64], imaging: Imaging, rng: np.random.Generator | None = None
            ) -> NDArray[np.uint8]:
    """Reflectance to an 8-bit image: levels, lighting gradient, Gaussian blur, noise, rounding.

    Works in float32 (grey levels need no more), which keeps a 1280x960 frame at a few ms.
    """
    img = (imaging.black_level + (imaging.white_level - imaging.black_level) * reflectance).astype(np.float32)
    if imaging.light_gradient:
        w = img.shape[1]
        ramp = 1.0 + imaging.light_gradient * (np.arange(w, dtype=np.float32) / max(w - 1, 1) - 0.5)
        img *= ramp[None, :]
    if imaging.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), imaging.blur_sigma_px)
    if imaging.noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng()
        # OpenCV's generator, seeded from ``rng``: the same frames for the same seed, 5x faster than numpy's.
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        noise = np.empty_like(img)
        cv2.randn(noise, 0.0, float(imaging.noise_sigma))
        img += noise
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


def render(camera: CameraModel, objects: Sequence[PlanarObject], imaging: Imaging | None = None,
           rng: np.random.Generator | None = None, supersample: int = 8) -> NDArray[np.uint8]:
    """Render planar objects seen by ``camera`` as an 8-bit grey image of ``camera.size``."""
    im = imaging if imaging is not None else Imaging()
    return to_grey(render_reflectance(camera, objects, im.background, supersample), im, rng)
