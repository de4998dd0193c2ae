"""The match score: edge-direction agreement over the visible model points (HALCON's metric).

HALCON's ``find_shape_model`` scores a pose by the mean, over the model points, of the cosine
between each model point's direction and the image gradient at the point's place, the gradient
normalised so that contrast does not matter. We do the same, with one change for real images:
the point looks for its edge (the ridge of the gradient across it) along its normal within
``SCORE_REACH_PX``, and the best agreement there counts, at full weight within ``SCORE_FULL_PX``
and then falling linearly to half at the reach. A real part differs from the taught one by a pixel here
and there (a burr, a solder fillet, lens distortion across the field, a blurred or JPEG-shifted
edge); at the exact point such a model point would see the flank of the edge, or nothing. The
direction must agree within ``SCORE_MAX_ANGLE_DEG`` (beyond, the point counts 0) and the
agreement is ``(cos - c0) / (1 - c0)``, 1 for a perfect match: random texture, whose gradients
point anywhere, then scores low even where it is strong.

Image gradients weaker than the contrast threshold count as no edge; at find the threshold is the
taught one, lowered where the image's own noise allows (``find_threshold``). The polarity rules are
HALCON's: ``use_polarity`` counts only gradients of the teach image's sign, ``ignore_global_polarity``
the better of all-one-sign and all-the-other, ``ignore_local_polarity`` each point either way.

Own code (numba): OpenCV has no rotation-invariant shape score.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from vision.image import gradients
from vision.shape.kernels import _bilinear2

F64 = NDArray[np.float64]

SCORE_REACH_PX = 1.5
"""How far along its normal a model point looks for its edge (level pixels)."""
SCORE_FULL_PX = 1.0
"""Within this distance the agreement counts fully; at the reach it counts half."""
SCORE_MAX_ANGLE_DEG = 30.0
"""Image gradients farther than this from the model direction count as no agreement."""
_STEP_PX = 0.25
NOISE_FACTOR = 4.0
"""At find, an image edge must be this many standard deviations of the gradient's noise strong
(below the taught contrast, when the image is cleaner than that asks: a blurred or low-contrast
part is still seen)."""
PART_FRACTION = 0.25
"""A faint part's edges count down to this fraction of their typical (75th percentile) strength."""
THRESHOLD_FLOOR = 0.5
"""Grey levels per pixel: the contrast threshold never drops below this (8-bit quantisation)."""
_GRAD_NOISE: dict[float, float] = {}


def noise_sigma(img: NDArray[np.uint8]) -> float:
    """The image's noise standard deviation in grey levels (Immerkaer's fast estimate: the mean
    absolute response of a mask that cancels locally linear intensity). Fine texture counts as noise
    here, which is what a contrast threshold should ignore."""
    h, w = img.shape
    if h < 3 or w < 3:
        return 0.0
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(img.astype(np.float32), -1, k, borderType=cv2.BORDER_REPLICATE)[1:-1, 1:-1]
    return float(math.sqrt(math.pi / 2.0) / 6.0 * np.mean(np.abs(r)))


def _grad_noise_per_grey(sigma: float) -> float:
    """Standard deviation of one component of ``image.gradients`` on unit white noise."""
    key = round(sigma, 3)
    if key not in _GRAD_NOISE:
        z = np.random.default_rng(0).normal(0.0, 1.0, (256, 256)).astype(np.float32)
        gx, _ = gradients(z, sigma)
        _GRAD_NOISE[key] = float(np.std(gx[8:-8, 8:-8]))
    return _GRAD_NOISE[key]


def grad_noise(crop: NDArray[np.uint8], sigma: float) -> float:
    """The gradient magnitude (grey levels / px, smoothing ``sigma``) that the noise of ``crop`` reaches:
    ``NOISE_FACTOR`` deviations of one gradient component (an edge weaker than this is not told from noise)."""
    return NOISE_FACTOR * _grad_noise_per_grey(sigma) * noise_sigma_sparse(crop)


def noise_sigma_sparse(img: NDArray[np.uint8], step: int = 3) -> float:
    """``noise_sigma`` from the mask's response at every ``step``-th row and column only (the same
    estimate from a ninth of the work; pick-speed)."""
    h, w = img.shape
    if h < 3 + step or w < 3 + step:
        return noise_sigma(img)
    ye, xe = h - 2, w - 2
    # the mask is the outer product of (1, -2, 1): along the rows, then the columns, in integers (exact, as the
    # float32 sums of whole grey levels it replaces: the same answer to the bit; pick-speed)
    v = (img[0:ye:step].astype(np.int16) - 2 * img[1:1 + ye:step].astype(np.int16)
         + img[2:2 + ye:step].astype(np.int16))
    r = (v[:, 0:xe:step] - 2 * v[:, 1:1 + xe:step] + v[:, 2:2 + xe:step]).astype(np.float32)
    return float(math.sqrt(math.pi / 2.0) / 6.0 * np.mean(np.abs(r)))


def find_threshold(crop: NDArray[np.uint8], sigma: float, taught: float, part_grad: float) -> float:
    """The gradient threshold (grey levels / px) for fitting and scoring in ``crop``: the taught one,
    lowered for a faint part (``part_grad``: the gradient magnitude typical of the candidate's edges)
    to ``PART_FRACTION`` of its edges, but never below ``NOISE_FACTOR`` noise deviations of this
    image (nor the floor). A part of good contrast keeps the taught threshold: a lower one would let
    weak texture beside its edges capture the fit."""
    if max(PART_FRACTION * part_grad, THRESHOLD_FLOOR) >= taught:
        return float(taught)  # the noise term cannot change the answer: skip its estimate (pick-speed)
    noise = NOISE_FACTOR * _grad_noise_per_grey(sigma) * noise_sigma(crop)
    return float(min(taught, max(PART_FRACTION * part_grad, noise, THRESHOLD_FLOOR)))


@njit(cache=True)
def point_agreement(G: NDArray[np.float32], q: F64, n: F64, thr: float, reach: float, full: float,
                    c0: float, step: float) -> tuple[F64, F64, F64, F64, F64]:
    """Per model point (image place ``q``, unit normal ``n``): the best agreement with an edge (a
    ridge of the gradient across it, above ``thr``) of the point's polarity and of the opposite
    one within ``reach`` along the normal, the distance (px, signed along ``n``) where each was
    seen, and the strongest gradient magnitude met along the normal (grey levels / px)."""
    npts = q.shape[0]
    gmax = np.zeros(npts)
    pos = np.zeros(npts)
    neg = np.zeros(npts)
    dpos = np.zeros(npts)
    dneg = np.zeros(npts)
    k = int(math.floor(reach / step + 1e-9))
    thr2 = thr * thr
    ns = 2 * k + 3
    gn = np.empty(ns)  # |gradient component along the normal| at t = (j - k - 1) * step
    cs = np.empty(ns)
    ms = np.empty(ns)
    for i in range(npts):
        nx, ny = n[i, 0], n[i, 1]
        for j in range(ns):
            t = (j - k - 1) * step
            gx, gy = _bilinear2(G, q[i, 0] + t * nx, q[i, 1] + t * ny)
            m2 = gx * gx + gy * gy
            s = gx * nx + gy * ny
            gn[j] = abs(s)
            ms[j] = m2
            if m2 > gmax[i]:
                gmax[i] = m2
            cs[j] = s / math.sqrt(m2) if m2 > 0.0 else 0.0
        for j in range(1, ns - 1):
            # only on the edge itself (the ridge of the gradient across it): a blurred edge's flank
            # would otherwise count from as far as the blur reaches
            # (within ~3 % of both neighbours: a step between two pixels leaves a plateau there)
            top = gn[j] / 0.97
            if ms[j] < thr2 or ms[j] <= 0.0 or top < gn[j - 1] or top < gn[j + 1]:
                continue
            t = (j - k - 1) * step
            c = cs[j]
            a = abs(t)
            w = 1.0 if a <= full else 1.0 - 0.5 * (a - full) / max(reach - full, 1e-9)
            v = (abs(c) - c0) / (1.0 - c0)
            if v <= 0.0:
                continue
            v *= w
            if c > 0.0:
                if v > pos[i]:
                    pos[i] = v
                    dpos[i] = t
            elif v > neg[i]:
                neg[i] = v
                dneg[i] = t
        gmax[i] = math.sqrt(gmax[i])
    return pos, neg, dpos, dneg, gmax


@dataclass
class PointDetail:
    """Per model point at a pose (the verification's input): the agreement counted in the score
    (0..1, polarity rule applied), the polarity seen (+1 as taught, -1 reversed, 0 no edge), the
    strongest gradient along the normal (grey levels / px) and whether the point is visible."""

    agree: F64
    sign: NDArray[np.int8]
    gmax: F64
    visible: NDArray[np.bool_]


def direction_detail(G: NDArray[np.float32], q: F64, n: F64, visible: NDArray[np.bool_], thr: float,
                     polarity: str, min_visible: float) -> tuple[float, int, int, PointDetail]:
    """``direction_score`` with the per-point detail it was summed from."""
    n_vis = int(np.count_nonzero(visible))
    c0 = math.cos(math.radians(SCORE_MAX_ANGLE_DEG))
    pos, neg, dpos, dneg, gmax = point_agreement(G, np.ascontiguousarray(q), np.ascontiguousarray(n), float(thr),
                                                 SCORE_REACH_PX, SCORE_FULL_PX, c0, _STEP_PX)
    pos = np.where(visible, pos, 0.0)
    neg = np.where(visible, neg, 0.0)
    agree_pos = (pos > 0) & (np.abs(dpos) <= 1.0)
    agree_neg = (neg > 0) & (np.abs(dneg) <= 1.0)
    if polarity == "ignore_local_polarity":
        use_pos = pos >= neg
    else:
        use_pos = np.full(len(pos), polarity == "use_polarity" or float(pos.sum()) >= float(neg.sum()))
    agree = np.where(use_pos, pos, neg)
    sign = np.where(agree > 0, np.where(use_pos, 1, -1), 0).astype(np.int8)
    detail = PointDetail(agree, sign, gmax, np.asarray(visible, dtype=np.bool_))
    if n_vis == 0 or n_vis < min_visible * len(visible):
        return 0.0, 0, n_vis, detail
    if polarity == "ignore_local_polarity":
        n_agree = int(np.count_nonzero(agree_pos | agree_neg))
    else:
        n_agree = int(np.count_nonzero(agree_pos if use_pos[0] else agree_neg))
    return float(agree.sum()) / n_vis, n_agree, n_vis, detail


def direction_score(G: NDArray[np.float32], q: F64, n: F64, visible: NDArray[np.bool_], thr: float,
                    polarity: str, min_visible: float) -> tuple[float, int, int]:
    """(score, agreeing points, visible points) of model points ``q`` with normals ``n`` on the
    two-channel gradient image ``G`` (the same pixels as ``q``). A point agrees when its edge is
    within 1 px with a direction inside the angle limit; the score is over the visible points."""
    s, n_agree, n_vis, _ = direction_detail(G, q, n, visible, thr, polarity, min_visible)
    return s, n_agree, n_vis
