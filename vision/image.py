"""Image helpers shared by the matchers: grey conversion, pyramids, gradients, sub-pixel sampling.

Pixel convention: the centre of the top-left pixel is ``(0, 0)``, x to the right, y down; a
pyramid level ``l`` pixel ``x`` lies at level-0 ``2**l * x`` (``cv2.pyrDown``).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import ImageError

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


def as_gray(image: NDArray[Any]) -> U8:
    """A single-channel uint8 view of ``image`` (BGR is converted; an empty image stays empty)."""
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise ImageError(f"an image must be H x W grey or H x W x 3 BGR, got an array of shape {image.shape}")
    if image.size == 0:
        return np.zeros((0, 0), np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


def pyramid(image: U8, n_levels: int) -> list[U8]:
    levels = [image]
    for _ in range(1, n_levels):
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def gradients(img: NDArray[Any], sigma: float) -> tuple[F32, F32]:
    """Scharr gradients in grey levels per pixel (after optional Gaussian smoothing)."""
    f = img.astype(np.float32)
    if sigma > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigma)
    gx = cv2.Scharr(f, cv2.CV_32F, 1, 0, scale=1.0 / 32.0)
    gy = cv2.Scharr(f, cv2.CV_32F, 0, 1, scale=1.0 / 32.0)
    return gx, gy


def magnitude(gx: F32, gy: F32) -> F32:
    """The gradient magnitude ``sqrt(gx*gx + gy*gy)`` in float32 (grey levels per pixel), the same
    bits at every buffer alignment. ``cv2.magnitude``'s are not: its last bit depends on where its
    output buffer lies (mod 64 bytes), and numpy's allocator places it differently from process to
    process, so a model taught from the same image differed in its last bits from run to run. Here
    each value is the correctly rounded square root of the float32 sum of the float32 squares
    (numpy's elementwise multiply, add and sqrt: IEEE operations, no fused multiply-add)."""
    m = np.multiply(gx, gx, dtype=np.float32)
    m += np.multiply(gy, gy, dtype=np.float32)
    return np.sqrt(m, out=m)


def bilinear(img: F32, x: F64, y: F64) -> F64:
    """Bilinear samples of ``img`` at (x, y) (pixel centres at integers; clamped at the border)."""
    h, w = img.shape
    x = np.minimum(np.maximum(x, 0.0), w - 1.001)
    y = np.minimum(np.maximum(y, 0.0), h - 1.001)
    x0 = x.astype(np.int64)
    y0 = y.astype(np.int64)
    fx = x - x0
    fy = y - y0
    i = y0 * w + x0
    flat = img.ravel()
    top = flat[i] + (flat[i + 1] - flat[i]) * fx
    bot = flat[i + w] + (flat[i + w + 1] - flat[i + w]) * fx
    return np.asarray(top + (bot - top) * fy, dtype=np.float64)


def bilinear2(img2: F32, x: F64, y: F64) -> F64:
    """Bilinear samples of a two-channel image (H, W, 2) -> (N, 2)."""
    h, w = img2.shape[:2]
    x = np.minimum(np.maximum(x, 0.0), w - 1.001)
    y = np.minimum(np.maximum(y, 0.0), h - 1.001)
    x0 = x.astype(np.int64)
    y0 = y.astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    i = y0 * w + x0
    flat = img2.reshape(-1, 2)
    a, b_, c, d = flat[i], flat[i + 1], flat[i + w], flat[i + w + 1]
    top = a + (b_ - a) * fx
    bot = c + (d - c) * fx
    return np.asarray(top + (bot - top) * fy, dtype=np.float64)


def gauss_peak(gm: F64, g0: F64, gp: F64) -> F64:
    """Sub-sample peak offset of three positive samples by a Gaussian (log-parabola) fit."""
    lm, l0, lp = np.log(np.maximum(gm, 1e-6)), np.log(np.maximum(g0, 1e-6)), np.log(np.maximum(gp, 1e-6))
    den = lm - 2 * l0 + lp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < -1e-9, 0.5 * (lm - lp) / den, 0.0)
    return np.clip(off, -0.5, 0.5)


CENTROID_HALF_WIDTH = 3


def centroid_offsets(img: F32, q: F64, n: F64, half_width: int = CENTROID_HALF_WIDTH
              ) -> tuple[F64, F64, F64]:
    """Edge offsets along the normals by the centroid of the intensity profile's differences.

    Samples ``img`` at ``q + t n`` for ``t = -K..K`` (bilinear) and returns
    ``(offset, contrast, differences)`` with ``offset = sum (t+1/2) D_t / sum D_t`` over the signed
    differences ``D_t`` of the profile. For a monotonic step that fits in the window this is exact
    whatever the edge's sub-pixel phase — unlike a peak fit, which aliases by a few hundredths of
    a pixel on sharp, pixel-integrated edges — and bilinear interpolation along an axis-aligned
    normal does not change it. ``contrast`` is the signed step ``I(K) - I(-K)``.
    """
    ts = np.arange(-half_width, half_width + 1, dtype=np.float64)
    sx = q[:, 0:1] + ts[None, :] * n[:, 0:1]
    sy = q[:, 1:2] + ts[None, :] * n[:, 1:2]
    prof = bilinear(img, sx.ravel(), sy.ravel()).reshape(sx.shape)
    D = np.diff(prof, axis=1)
    S = D.sum(axis=1)
    mid = ts[:-1] + 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(np.abs(S) > 1e-9, (D @ mid) / S, 0.0)
    return off, S, D


def rot(theta: float) -> F64:
    """Rotation counter-clockwise on screen by ``theta`` rad (cv2.getRotationMatrix2D sense)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s], [-s, c]])


def wrap_deg(a: float) -> float:
    a = math.fmod(a, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return a



def profile_ok(img: F32, q: F64, n: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Centroid offsets, contrasts and whether each profile is one clean monotonic step."""
    off, S, D = centroid_offsets(img, q, n)
    wrong = np.clip(-D * np.sign(S)[:, None], 0, None).sum(axis=1)
    clean = wrong <= 0.1 * np.abs(S)
    return off, S, clean
