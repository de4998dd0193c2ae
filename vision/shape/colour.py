"""Colour teach and search images: the one channel the matcher sees (``TeachParams.colour``).

The matcher works on one channel (pyramids, gradients, the intensity profiles its edge fit centres
on, the taught patch's grey values). From a colour image that channel is, by default, the grey
value (``as_gray``). A part that differs from its background in colour more reliably than in
brightness (a grey metal head in orange wood under one-sided light: the shading and the head's
shadow move its grey edges) can be seen in a **chroma** channel instead: the colour image
projected on one direction of colour space, fixed at teach time:

- orthogonal to the **background's colour**, so that the background's shading and the shadows on
  it (which scale its colour, i.e. move it along that direction) vanish from the channel. The
  background's colour is the top eigenvector of the second moment of the teach ROIs' outer ring
  (``RING_PX``; a teach ROI frames the part with some background around it);
- within that plane, the direction along which the ROIs' edges are strongest: the top eigenvector
  of the ROIs' colour structure tensor (Di Zenzo's tensor summed over the ROI, ``sum J^T J`` with
  ``J`` the 2 x 3 Jacobian of the blurred B, G, R channels) projected onto the plane.

Why not the multichannel gradient itself (HALCON's shape models on a colour image): its tensor's top
eigenvector is nearly the grey axis on most scenes (96 % of the screw ROIs' edge energy), so it
sees the shading as the grey image does; and a per-pixel colour gradient has no scalar image whose
profiles the edge fit and the patch fit could sample, whereas a fixed projection keeps every later
step as it is at the cost of one ``cv2.transform`` per image. Why not the grey axis projected out
(the plain chroma): a dark hole in the wood is as colourless as the grey head there, and was found
as one (5 false matches in the screw corpus's variants; with the background's colour projected out,
1: ``bench/results/pick_real.md``).

``TeachParams.colour``:

- ``"grey"`` (default): the grey value, as before; always so for a grey image, or a colour one whose
  channels are equal;
- ``"chroma"``: the chroma projection (the teach images must be in colour);
- ``"auto"``: the chroma when the ROIs' chroma edges are strong enough to make a model on their own
  (the 99th percentile of their gradient reaches ``CHROMA_MARGIN`` times the model's contrast
  floor, ``min_contrast`` as a gradient), else the grey value.

The model keeps the projection (``ShapeModel.colour``, a model file's ``shape.colour``), and
``search.find`` applies it to a colour image; a grey image given to a chroma model is searched as
it is (its grey values: the model's edges are colour edges, so expect no match).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import U8, as_gray

COLOUR_MODES = ("grey", "chroma", "auto")
CHROMA_MARGIN = 2.0
"""``auto`` takes the chroma when its ROI's strong edges (99th percentile of the gradient) reach this
multiple of the model's contrast floor: an edge that only just passes the floor is noise-limited."""
RING_PX = 4
"""The outer ring of a teach ROI (px) whose colours are taken as the part's background."""


@dataclass(frozen=True)
class ColourMix:
    """One channel from a B, G, R image: ``offset + weights . (B, G, R)`` (grey levels, rounded, clipped
    to 0..255). The weights' absolute values sum to 1 and the offset keeps every colour in range."""

    weights_bgr: tuple[float, float, float]
    offset: float

    def apply(self, image: NDArray[Any]) -> U8:
        """The channel of a colour image (H x W x 3 BGR or x 4 BGRA, uint8)."""
        bgr = np.ascontiguousarray(np.asarray(image)[:, :, :3])
        if bgr.dtype != np.uint8:
            bgr = np.clip(bgr, 0, 255).astype(np.uint8)
        m = np.array([[*self.weights_bgr, self.offset]], np.float64)
        return np.asarray(cv2.transform(bgr, m), dtype=np.uint8).reshape(bgr.shape[:2])

    def to_dict(self) -> dict[str, Any]:
        return {"weights_bgr": [round(w, 6) for w in self.weights_bgr], "offset": round(self.offset, 4)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ColourMix:
        w = [float(x) for x in d.get("weights_bgr", ())]
        if len(w) != 3 or not np.all(np.isfinite(w)) or abs(sum(abs(x) for x in w) - 1.0) > 1e-3:
            raise TeachError(f"the model's colour weights {d.get('weights_bgr')!r} are corrupt: teach the part again")
        return cls((w[0], w[1], w[2]), float(d.get("offset", 0.0)))


def is_colour(image: NDArray[Any]) -> bool:
    """Whether ``image`` is a colour image whose channels differ (a grey picture stored as BGR is not)."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] < 3 or a.size == 0:
        return False
    return not (np.array_equal(a[:, :, 0], a[:, :, 1]) and np.array_equal(a[:, :, 1], a[:, :, 2]))


def _tensor(image: NDArray[Any], roi: tuple[float, float, float, float], sigma: float
            ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The ROI's colour gradients (N, 3) in x and y (B, G, R grey levels per px, ``image.gradients``'
    scale) and its colour structure tensor (3, 3) summed over the ROI."""
    u, v, w, h = roi
    H, W = np.asarray(image).shape[:2]
    x0, y0 = max(int(np.floor(u)), 0), max(int(np.floor(v)), 0)
    x1, y1 = min(int(np.ceil(u + w)), W), min(int(np.ceil(v + h)), H)
    pad = 3 + int(np.ceil(3 * sigma))
    f = np.asarray(image)[max(y0 - pad, 0):min(y1 + pad, H), max(x0 - pad, 0):min(x1 + pad, W), :3]
    f = f.astype(np.float32)
    if sigma > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigma)
    oy, ox = y0 - max(y0 - pad, 0), x0 - max(x0 - pad, 0)
    gx = cv2.Scharr(f, cv2.CV_32F, 1, 0, scale=1.0 / 32.0)[oy:oy + y1 - y0, ox:ox + x1 - x0]
    gy = cv2.Scharr(f, cv2.CV_32F, 0, 1, scale=1.0 / 32.0)[oy:oy + y1 - y0, ox:ox + x1 - x0]
    gx64 = gx.reshape(-1, 3).astype(np.float64)
    gy64 = gy.reshape(-1, 3).astype(np.float64)
    return gx64, gy64, gx64.T @ gx64 + gy64.T @ gy64


def _ring(image: NDArray[Any], roi: tuple[float, float, float, float], width: int = RING_PX) -> NDArray[np.float64]:
    """The B, G, R values (N, 3) of the ROI's outer ``width`` px: mostly the part's background."""
    u, v, w, h = roi
    H, W = np.asarray(image).shape[:2]
    x0, y0 = max(int(np.floor(u)), 0), max(int(np.floor(v)), 0)
    x1, y1 = min(int(np.ceil(u + w)), W), min(int(np.ceil(v + h)), H)
    crop = np.asarray(image)[y0:y1, x0:x1, :3].astype(np.float64)
    inner = np.zeros(crop.shape[:2], bool)
    inner[width:-width, width:-width] = True
    return crop[~inner]


def chroma_mix(images: Sequence[NDArray[Any]], rois: Sequence[tuple[float, float, float, float]],
               sigma: float) -> tuple[ColourMix, float]:
    """The chroma projection of the teach views (the module) and the 99th percentile of its gradient
    over their ROIs (grey levels of the projected channel per px)."""
    grads = [_tensor(img, roi, sigma) for img, roi in zip(images, rois, strict=True)]
    ring = np.concatenate([_ring(img, roi) for img, roi in zip(images, rois, strict=True)])
    _, Vb = np.linalg.eigh(ring.T @ ring)
    background = Vb[:, -1]  # the background's colour (its shading scales it along this direction)
    P = np.eye(3) - np.outer(background, background)
    M = P @ sum((g[2] for g in grads), np.zeros((3, 3))) @ P
    _, V = np.linalg.eigh(M)
    w = V[:, -1]
    w = np.round(w * (1.0 if w[int(np.argmax(np.abs(w)))] > 0 else -1.0) / float(np.abs(w).sum()), 6)
    # (rounded as the model file keeps them: a model read back sees the same channel)
    mix = ColourMix((float(w[0]), float(w[1]), float(w[2])), round(255.0 * float(np.clip(-w, 0, None).sum()), 4))
    mag = np.concatenate([np.hypot(gx @ w, gy @ w) for gx, gy, _ in grads])
    return mix, float(np.percentile(mag, 99)) if len(mag) else 0.0


def taught_mix(images: Sequence[NDArray[Any]], rois: Sequence[tuple[float, float, float, float]], mode: str,
               sigma: float, floor_grad: float) -> ColourMix | None:
    """The projection a model taught from ``images`` (their ROIs) with ``TeachParams.colour`` = ``mode``
    keeps, or ``None`` for the grey value; ``floor_grad``: the model's contrast floor as a gradient
    (grey levels per px)."""
    if mode not in COLOUR_MODES:
        raise TeachError(f"colour {mode!r} must be one of {', '.join(COLOUR_MODES)}")
    colour = all(is_colour(i) for i in images)
    if mode == "chroma" and not colour:
        raise TeachError("colour='chroma' needs colour teach images (H x W x 3 BGR with channels that differ): "
                         "give the camera's colour image, or teach with colour='grey'")
    if mode == "grey" or not colour:
        return None
    mix, strength = chroma_mix(images, rois, sigma)
    if mode == "chroma" or strength >= CHROMA_MARGIN * floor_grad:
        return mix
    return None


def channel(image: NDArray[Any], mix: ColourMix | None) -> U8:
    """The one channel the matcher sees of ``image``: ``mix`` applied to a colour image, else its grey
    value (``as_gray``, which also checks the image's shape)."""
    a = np.asarray(image)
    if mix is None or a.ndim != 3 or a.shape[2] < 3 or a.size == 0:
        return as_gray(a)
    as_gray(a[:1, :1])  # the same shape checks as a grey conversion
    return mix.apply(a)
