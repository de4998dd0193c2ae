"""Colour teach and search images: the one channel the matcher sees (``TeachParams.colour``).

The matcher works on one channel (pyramids, gradients, the intensity profiles its edge fit centres
on, the taught patch's grey values). From a colour image that channel is the grey value
(``as_gray``) unless the taught part is coloured against its background (``auto``, the default). A
part that differs from its background in colour more reliably than in brightness (a grey metal head
in orange wood under one-sided light: the shading and the head's shadow move its grey edges) can be
seen in a **chroma** channel instead: the colour image projected on one direction of colour space,
fixed at teach time:

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

- ``"grey"``: the grey value (the default before session 16); always so for a grey image, or a colour
  one whose channels are equal;
- ``"chroma"``: the chroma projection (the teach images must be in colour);
- ``"auto"`` (default): the chroma when the ROIs' chroma edges are strong enough to make a model on their own
  (the 99th percentile of their gradient reaches ``CHROMA_MARGIN`` times the model's contrast
  floor, ``min_contrast`` as a gradient), else the grey value.

The model keeps the projection (``ShapeModel.colour``, a model file's ``shape.colour``), and
``search.find`` applies it to a colour image; a grey image given to a chroma model is searched as
it is (its grey values: the model's edges are colour edges, so expect no match).

**The interior of a colour model's match** (``interior_verdict``, in ``search.find``'s verification after
``verify.verify``): on the chroma channel a part's outline can be matched by something of another colour
inside the same outline: an empty screw hole whose torn, pale rim is as colourless as the zinc head, with
a dark centre where the head is uniform (at a quarter size the only false matches of the screw corpus's
colour models: ``bench/results/pick_real.md``, "Colour by default?"). Its edges pass every check of
``verify`` (they are real edges, 4-15x the noise, all round). What tells it apart is the part's inside:
with the background's shading projected out the taught patch (the part's pixels in the model's channel)
is the part's colour, so a colour model's match must correlate with it (``INTERIOR_MIN_NCC``, over every
pixel of the part, flat ones included) at the turn where the patch's own samples correlate best (a round
part's edges do not fix its turn). A grey model is not asked this: its
interior is the light's as much as the part's (``patch.MIN_PATCH_NCC`` only decides whether the patch
finishes the pose).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import U8, as_gray, bilinear
from vision.shape.patch import BLUR_SIGMA_PX, MAX_SAMPLES, MIN_PATCH_NCC, TeachPatch
from vision.shape.score import PointDetail

COLOUR_MODES = ("grey", "chroma", "auto")
CHROMA_MARGIN = 2.0
"""``auto`` takes the chroma when its ROI's strong edges (99th percentile of the gradient) reach this
multiple of the model's contrast floor: an edge that only just passes the floor is noise-limited."""
RING_PX = 4
SCAN_SAMPLES = 800
"""The patch samples ``interior_ncc`` scans the turn with (``patch._angle_scan``'s subset)."""
INTERIOR_MIN_NCC = 0.5 * MIN_PATCH_NCC
"""The least correlation of a colour model's taught patch with a match's interior (``interior_verdict``):
half of what the patch fit asks to finish a pose under the teach light. Measured (``bench/pick_real.py``'s
screw heads in colour, several views and one ROI, every variant and size): the 82 real heads found 0.44 and more,
the two empty holes the edges matched -0.08 and 0.12. (A regular ring of the head's colour around a dark
bore of 0.6-0.7 of its radius, rendered, still correlates 0.25-0.45: the check sees a centre of another
colour covering most of the inside, not a thin one.)"""
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


def interior_ncc(patch: TeachPatch, pyr: list[U8], x: float, y: float, theta: float, scale: float,
                 reversed_: bool) -> float:
    """The normalised correlation of the taught ``patch`` (the part's pixels in the model's channel) with
    the image (``pyr``: its pyramid in the model's channel) at a match whose reference point lies at
    ``(x, y)`` (level-0 px), turned by ``theta`` (rad) and scaled by ``scale``, at the turn where it
    correlates best (as ``patch._angle_scan`` finds it), on the patch's fit level; ``reversed_``: the match's edges are
    the taught ones reversed (an inverted image), so the image is taken reversed. 0 when too little of the
    patch lies inside the image."""
    lv = min(patch.fit_level(), len(pyr) - 1)
    f = 2.0 ** lv
    pl = patch.at_level(lv)
    pts, values, _ = pl.samples()
    if len(pts) < 30:
        return 0.0
    r = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) * scale + 4.0
    img = pyr[lv]
    h, w = img.shape
    cx, cy = x / f, y / f
    x0, y0 = max(int(cx - r), 0), max(int(cy - r), 0)
    x1, y1 = min(int(cx + r) + 2, w), min(int(cy + r) + 2, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return 0.0
    crop = img[y0:y1, x0:x1]
    if reversed_:
        crop = 255 - crop
    f32 = crop.astype(np.float32)
    # the turn: the patch's own samples (at most SCAN_SAMPLES of them) over the whole turn, in steps that
    # move the outermost one about a pixel and a half, on the image smoothed twice as much (patch._angle_scan's
    # scan, every turn at once)
    sub = np.linspace(0, len(pts) - 1, min(len(pts), SCAN_SAMPLES)).astype(np.int64)
    n = max(int(math.ceil(2 * math.pi * (r - 4.0) / 1.5)), 36)
    turns = np.asarray(theta + np.arange(n) * (2 * math.pi / n), dtype=np.float64)
    scan = _correlations(cv2.GaussianBlur(f32, (0, 0), 2.0 * BLUR_SIGMA_PX), pts[sub], values[sub],
                         cx - x0, cy - y0, turns, scale)
    inside, taught = _interior(pl)
    smooth = cv2.GaussianBlur(f32, (0, 0), BLUR_SIGMA_PX)
    best = turns[int(np.argmax(scan))]
    return float(_correlations(smooth, inside, taught, cx - x0, cy - y0, np.array([best]), scale)[0])


def _correlations(img: NDArray[np.float32], pts: NDArray[np.float64], values: NDArray[np.float64], x: float,
                  y: float, turns: NDArray[np.float64], scale: float) -> NDArray[np.float64]:
    """The normalised correlation of ``values`` with ``img`` sampled (bilinear) at ``pts`` (relative to the
    reference point) turned by each of ``turns`` (rad, ``patch``'s convention) and scaled by ``scale`` about
    ``(x, y)`` (``img``'s px): one per turn, 0 where either side is flat."""
    c, s = np.cos(turns)[:, None], np.sin(turns)[:, None]
    qx = x + scale * (c * pts[None, :, 0] + s * pts[None, :, 1])
    qy = y + scale * (-s * pts[None, :, 0] + c * pts[None, :, 1])
    v = bilinear(img, qx.ravel(), qy.ravel()).reshape(len(turns), len(pts))
    v -= v.mean(axis=1, keepdims=True)
    t = values - values.mean()
    den = np.sqrt((v * v).sum(axis=1) * float(t @ t))
    return np.where(den > 0, (v @ t) / np.where(den > 0, den, 1.0), 0.0)


def _interior(patch: TeachPatch) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every pixel of the patch's part (its mask; on a grid sparse enough to keep at most ``MAX_SAMPLES``),
    flat ones included (the patch's own samples leave the flat inside of a uniform part out): points
    (N, 2) relative to the reference point and their smoothed values (cached)."""
    got = patch.__dict__.get("_interior")
    if got is not None:
        return got  # type: ignore[no-any-return]
    step = max(1, int(math.ceil(math.sqrt(int(patch.mask.sum()) / MAX_SAMPLES))))
    grid = np.zeros_like(patch.mask)
    grid[::step, ::step] = True
    ys, xs = np.nonzero(patch.mask & grid)
    smooth = cv2.GaussianBlur(patch.image.astype(np.float32), (0, 0), BLUR_SIGMA_PX)
    out = (np.stack([xs + patch.origin[0], ys + patch.origin[1]], axis=1).astype(np.float64),
           smooth[ys, xs].astype(np.float64))
    patch.__dict__["_interior"] = out
    return out


def interior_verdict(patch: TeachPatch | None, pyr: list[U8], x: float, y: float, theta: float, scale: float,
                     detail: PointDetail, scores: dict[str, float]) -> str | None:
    """Why a colour model's match is not the part (its interior does not correlate with the taught
    patch, ``INTERIOR_MIN_NCC``), or None; the correlation joins ``scores`` as ``interior``. The match's
    pose as ``interior_ncc``'s; ``detail``: its edge points' detail (``score.PointDetail``), whose seen
    polarity tells a reversed image. A model without a patch (a file taught before patches) is not judged."""
    if patch is None:
        return None
    seen = (detail.agree > 0) & detail.visible
    reversed_ = int(np.count_nonzero(detail.sign[seen] < 0)) > int(np.count_nonzero(detail.sign[seen] > 0))
    ncc = interior_ncc(patch, pyr, x, y, theta, scale, reversed_)
    scores["interior"] = round(ncc, 4)
    if ncc >= INTERIOR_MIN_NCC:
        return None
    return (f"its interior is not the part's colour: the taught patch correlates {ncc:.2f} < {INTERIOR_MIN_NCC:g} "
            "with it at its best turn (something of another colour inside the part's outline)")
