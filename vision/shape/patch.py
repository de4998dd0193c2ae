"""The taught patch: the part's interior, used to finish a match's pose and to say how good it is.

A shape model's edges fix a pose well where the outline is crisp, and poorly where it is rounded, low
in contrast, nearly symmetric, or where texture and shading beside it pull the edge fit. The part's
interior (its print, holes, facets) still says where it is. ``TeachPatch`` keeps the teach image's
pixels of the part (the ROI, masked to the hull of the level-0 model points) as sample points with
their grey values; ``fit`` aligns them to the image by Gauss-Newton on the grey values (a
similarity: position, angle, scale; with a gain and an offset for the light, and Tukey weights so
that glints, clutter and an occluder take no part), from the edge fit's pose, at full resolution.

Its answer carries:

- ``ncc``: the normalised correlation of the patch at the final pose (1: the part as taught);
- the pose's covariance by a **block jackknife**: the patch's sample points are split into blocks
  (a grid over the part), the fit is solved again without each block (one Gauss-Newton step from the
  optimum, which is exact to first order), and the spread of those answers is the pose's variance.
  Errors that are common to neighbouring pixels (blur, a shading gradient, a texture the model lacks)
  show in it, where the textbook ``s^2 (J^T J)^-1`` would assume every pixel independent and report a
  hundredth of a degree for a fit that is off by half a degree.

``uncertainty.merge`` merges the edge fit and the patch fit by their covariances and carries their
disagreement beyond what their own covariances allow in the result's covariance (a random-effects merge):
a pose the two methods disagree on says so in its 1-sigma. Units: pixels of the image (level 0), angles in
radians inside, degrees in ``Match``.
"""

from __future__ import annotations

import base64
import binascii
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import F64, U8, bilinear
from vision.shape import cov_kernels as ck
from vision.shape import patch_kernels as pk
from vision.shape.uncertainty import JACKKNIFE_BLOCKS, blocks_of, merge, sigma_of

MAX_SAMPLES = 1500
"""Sample points of a patch (a large part is subsampled on a grid: its fit's cost is bounded)."""
TUKEY_C = 4.685
"""Tukey's biweight constant (in robust standard deviations of the residual)."""
BLUR_SIGMA_PX = 1.0
"""Patch and image are smoothed alike before the fit: bilinear interpolation of a sharp image pulls a
grey-value fit towards whole pixels (a few hundredths of a pixel on rendered edges); smoothed, it does
not."""
TILT_PRIOR = 0.01
"""The patch fit's prior 1-sigma of its perspective terms, as the change of scale across the part."""
HULL_MARGIN_PX = 2.0
"""The patch's mask is the hull of the model's level-0 points grown by this much (the outline's own
grey-level step is in the patch)."""


@dataclass
class TeachPatch:
    """The part's pixels in the teach image, relative to the reference point (level-0 pixels)."""

    image: U8
    """The teach image's crop (H, W) around the ROI."""
    origin: tuple[float, float]
    """Where the crop's pixel (0, 0) lies relative to the reference point (x, y)."""
    mask: NDArray[np.bool_]
    """(H, W) the part's pixels (the model's hull, grown by ``HULL_MARGIN_PX``, inside the ROI)."""

    def samples(self) -> tuple[F64, F64, F64]:
        """Sample points (N, 2) relative to the reference point, their grey values and their
        gradient magnitudes (cached): the mask's pixels where the teach image is not flat, on a
        grid sparse enough to keep at most ``MAX_SAMPLES``."""
        got = self.__dict__.get("_samples")
        if got is not None:
            return got  # type: ignore[no-any-return]
        f = cv2.GaussianBlur(self.image.astype(np.float32), (0, 0), BLUR_SIGMA_PX)
        gx = cv2.Scharr(f, cv2.CV_32F, 1, 0, scale=1.0 / 32.0)
        gy = cv2.Scharr(f, cv2.CV_32F, 0, 1, scale=1.0 / 32.0)
        mag = np.hypot(gx, gy)
        inner = self.mask.copy()
        inner[:1, :] = inner[-1:, :] = False
        inner[:, :1] = inner[:, -1:] = False
        vals = mag[inner]
        # a flat pixel says nothing of the pose: keep those above the patch's own noise
        floor = max(float(np.percentile(vals, 25)) if vals.size else 0.0, 1.0)
        keep = inner & (mag > floor)
        n = int(keep.sum())
        step = max(1, int(math.ceil(math.sqrt(n / MAX_SAMPLES)))) if n else 1
        grid = np.zeros_like(keep)
        grid[::step, ::step] = True
        ys, xs = np.nonzero(keep & grid)
        pts = np.stack([xs + self.origin[0], ys + self.origin[1]], axis=1).astype(np.float64)
        out = (pts, f[ys, xs].astype(np.float64), mag[ys, xs].astype(np.float64))
        self.__dict__["_samples"] = out
        return out

    def at_level(self, level: int) -> TeachPatch:
        """The patch on pyramid level ``level`` (``cv2.pyrDown`` as the search's pyramid: level-``l`` pixel
        ``x`` lies at level-0 ``2**l x``); cached."""
        if level == 0:
            return self
        cache = self.__dict__.setdefault("_levels", {})
        got = cache.get(level)
        if got is None:
            img, mask = self.image, self.mask.astype(np.uint8)
            for _ in range(level):
                img = cv2.pyrDown(img)
            mask = cv2.resize(mask, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
            f = 2.0 ** level
            got = TeachPatch(img, (self.origin[0] / f, self.origin[1] / f), mask.astype(bool))
            cache[level] = got
        return got  # type: ignore[no-any-return]

    def fit_level(self) -> int:
        """The pyramid level whose pixels the samples cover densely (grid step about one pixel): a large
        part is fitted on a coarser level, where ``MAX_SAMPLES`` still sample it without gaps."""
        got = self.__dict__.get("_fit_level")
        if got is None:
            n = int(self.mask.sum())
            got = max(int(math.floor(math.log2(max(math.sqrt(n / MAX_SAMPLES), 1.0)))), 0)
            self.__dict__["_fit_level"] = got
        return got  # type: ignore[no-any-return]

    def mirrored(self) -> TeachPatch:
        """The patch of the part's mirror image (x -> -x about the reference point)."""
        w = self.image.shape[1]
        return TeachPatch(self.image[:, ::-1].copy(), (-(self.origin[0] + w - 1), self.origin[1]),
                          self.mask[:, ::-1].copy())


def make_patch(img: U8, roi: tuple[float, float, float, float], model_pts: F64) -> TeachPatch:
    """The teach patch of ``roi`` in ``img``; ``model_pts``: the level-0 model points relative to the
    reference point (their hull is the part)."""
    u, v, w, h = roi
    ref = (u + w / 2.0, v + h / 2.0)
    x0, y0 = max(int(math.floor(u)), 0), max(int(math.floor(v)), 0)
    x1, y1 = min(int(math.ceil(u + w)), img.shape[1]), min(int(math.ceil(v + h)), img.shape[0])
    return patch_from(np.ascontiguousarray(img[y0:y1, x0:x1]), (x0 - ref[0], y0 - ref[1]), model_pts)


def patch_from(crop: U8, origin: tuple[float, float], model_pts: F64) -> TeachPatch:
    """The patch of a teach-image ``crop`` whose pixel (0, 0) lies at ``origin`` from the reference
    point, masked to the hull of the level-0 ``model_pts`` grown by ``HULL_MARGIN_PX``."""
    mask = np.zeros(crop.shape, np.uint8)
    hull = cv2.convexHull((model_pts - np.array(origin)).astype(np.float32))
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    k = 2 * int(math.ceil(HULL_MARGIN_PX)) + 1
    mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return TeachPatch(crop, (float(origin[0]), float(origin[1])), mask.astype(bool))


def patch_to_dict(p: TeachPatch) -> dict[str, Any]:
    """The patch as a model file stores it: the crop as a base64 PNG and its origin (the mask is the
    model's hull again when read)."""
    ok, buf = cv2.imencode(".png", p.image)
    if not ok:  # pragma: no cover - a uint8 image always encodes
        raise TeachError("the teach patch could not be encoded as PNG")
    return {"origin_px": [round(p.origin[0], 4), round(p.origin[1], 4)],
            "png_base64": base64.b64encode(buf.tobytes()).decode("ascii")}


def patch_from_dict(d: dict[str, Any], model_pts: F64) -> TeachPatch:
    """The patch of a model file (``patch_to_dict``); a corrupt one raises ``TeachError``."""
    try:
        raw = base64.b64decode(str(d["png_base64"]), validate=True)
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)
        origin = (float(d["origin_px"][0]), float(d["origin_px"][1]))
    except (KeyError, TypeError, ValueError, IndexError, binascii.Error) as e:
        raise TeachError(f"the model's teach patch is corrupt ({e}): teach the part again") from e
    if img is None or img.ndim != 2 or min(img.shape) < 2:
        raise TeachError("the model's teach patch is not a grey PNG: teach the part again")
    return patch_from(np.ascontiguousarray(img, dtype=np.uint8), origin, model_pts)


def patch_blocks(patch: TeachPatch) -> NDArray[np.int64]:
    """Each sample's jackknife block (cached with the samples)."""
    got = patch.__dict__.get("_blocks")
    if got is None:
        got = blocks_of(patch.samples()[0])
        patch.__dict__["_blocks"] = got
    return got  # type: ignore[no-any-return]


def patch_step(patch: TeachPatch) -> float:
    """The samples' grid step (px; cached with the samples)."""
    got = patch.__dict__.get("_step")
    if got is None:
        pts = patch.samples()[0]
        got = float(np.median(np.hypot(*np.diff(pts[: min(len(pts), 200)], axis=0).T))) if len(pts) > 2 else 1.0
        patch.__dict__["_step"] = got
    return got  # type: ignore[no-any-return]


@dataclass
class PatchFit:
    """The patch's fit at a pose (level-0 image pixels; ``theta`` rad, CCW on screen)."""

    x: float
    y: float
    theta: float
    scale: float
    ncc: float
    """Normalised correlation of the patch's samples with the image at the final pose."""
    cov: F64
    """(3, 3) covariance of (x, y, theta) by the block jackknife."""
    n_used: int
    """Samples with weight > 0 at the end."""
    converged: bool


def _warp(pts: F64, x: float, y: float, th: float, sc: float) -> tuple[F64, F64]:
    """Sample points at a pose, and d(point)/d(theta) (image pixels)."""
    c, s = math.cos(th), math.sin(th)
    rx = c * pts[:, 0] + s * pts[:, 1]
    ry = -s * pts[:, 0] + c * pts[:, 1]
    q = np.stack([sc * rx + x, sc * ry + y], axis=1)
    dth = np.stack([sc * ry, -sc * rx], axis=1)
    return q, dth


def fit(patch: TeachPatch, image: U8, x: float, y: float, theta: float, scale: float,
        iterations: int = 8) -> PatchFit | None:
    """Align the patch to ``image`` from the pose (x, y, theta, scale) by a plane homography of its
    samples, ``q = (A p + t) / (1 + v.p)`` (a slightly tilted view; the turn and scale reported are
    those of its local linear map at the reference point, as for the edge fit's homography); ``None``
    when too little of it lies inside the image or the fit runs away (more than the part's size from
    the start)."""
    pts, T, _ = patch.samples()
    if len(pts) < 30:
        return None
    r_max = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) * scale * 1.2 + 4
    h, w = image.shape
    x0, y0 = max(int(x - r_max), 0), max(int(y - r_max), 0)
    x1, y1 = min(int(x + r_max) + 2, w), min(int(y + r_max) + 2, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    crop = cv2.GaussianBlur(image[y0:y1, x0:x1].astype(np.float32), (0, 0), BLUR_SIGMA_PX)
    gx = cv2.Scharr(crop, cv2.CV_32F, 1, 0, scale=1.0 / 32.0)
    gy = cv2.Scharr(crop, cv2.CV_32F, 0, 1, scale=1.0 / 32.0)
    c, s = math.cos(theta), math.sin(theta)
    # (t, A, v, gain, offset): see patch_kernels
    par = np.array([x - x0, y - y0, scale * c, scale * s, -scale * s, scale * c, 0.0, 0.0, 1.0, 0.0])
    block = patch_blocks(patch)
    # the Gauss-Newton loop, compiled (pick speed; a singular step is a failure, status -1)
    status, par, H, g, Hb, Gb, r, inside, sd, ncc, sw, swr, cnt = pk.gauss_newton(
        crop, gx, gy, pts, T, block, JACKKNIFE_BLOCKS ** 2, par, iterations, TUKEY_C, r_max, scale, TILT_PRIOR)
    if status < 0:
        return None
    converged = status == 1
    t, A, v = par[:2], par[2:6].reshape(2, 2), par[6:8]
    # ncc: a I + b at the final pose against the patch (pk.ncc_of)
    # the turn and scale of the local linear map at the reference point, Lm = A - t v^T (as the edge
    # fit's homography); (x, y, theta) from (t, A, v, a, b) to first order
    Lm = A - np.outer(t, v)
    th = math.atan2(-Lm[1, 0], Lm[0, 0])
    rr = Lm[0, 0] ** 2 + Lm[1, 0] ** 2
    g00, g10 = Lm[1, 0] / rr, -Lm[0, 0] / rr
    M = np.zeros((3, 10))
    M[0, 0] = M[1, 1] = 1.0
    M[2, 2], M[2, 4] = g00, g10
    M[2, 0], M[2, 1] = -v[0] * g00, -v[0] * g10
    M[2, 6] = -t[0] * g00 - t[1] * g10
    # samples closer than the blur's reach share their errors: samples per independent one
    # sw, swr, cnt: pk.weighted_rss's, from gauss_newton
    if cnt <= 12:
        return None
    s2 = swr / max(sw * (cnt - 10) / cnt, 1e-12)
    corr = max((2.0 * BLUR_SIGMA_PX / max(min(patch_step(patch), 4.0), 0.5)) ** 2, 1.0)
    cov = ck.honest_systems(H, g, Hb, Gb, s2, corr, M)
    return PatchFit(float(t[0] + x0), float(t[1] + y0), th, math.sqrt(abs(float(np.linalg.det(Lm)))), ncc, cov,
                    cnt, converged)


def _ncc(a: F64, b: F64) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else 0.0


SCAN_SIGMA_DEG = 1.0
"""Where the edge fit's angle 1-sigma exceeds this, the patch's correlation is scanned over the whole
turn first (``_angle_scan``): the outline does not fix the angle, the interior may."""
SPLIT_CHI2 = 25.0
"""Edge fit and patch fit disagreeing by more than this chi-square per degree of freedom (5 sigma) are
not averaged: the sharper one in angle answers (``finish``)."""
MIN_PATCH_NCC = 0.5
"""A patch fit correlating less than this with the image is not used (a part seen under another light
or much hidden: the edge fit alone answers, its own 1-sigma stands)."""


def _fit_at(patch: TeachPatch, pyr: list[U8], lv: int, x: float, y: float, theta: float, scale: float
            ) -> PatchFit | None:
    """``fit`` on pyramid level ``lv`` (``pyr``: the image's pyramid), answered in level-0 pixels."""
    f = 2.0 ** lv
    pf = fit(patch.at_level(lv), pyr[lv], x / f, y / f, theta, scale)
    if pf is None or lv == 0:
        return pf
    S = np.diag([f, f, 1.0])
    return PatchFit(pf.x * f, pf.y * f, pf.theta, pf.scale, pf.ncc, S @ pf.cov @ S, pf.n_used, pf.converged)


_COV_FLOOR = np.diag([1e-6, 1e-6, 1e-10])
"""``finish``'s floor of each fit's covariance (px^2, px^2, rad^2; read only)."""


def finish(patch: TeachPatch, pyr: list[U8], x: float, y: float, theta: float, scale: float,
           cov_edge: F64 | None, T0: F64 | None = None
           ) -> tuple[float, float, float, float, float, dict[str, float]] | None:
    """The final pose from the edge fit's ``(x, y, theta, scale)`` (level-0 px, rad) and its covariance,
    and the patch fit from there (on the image's pyramid ``pyr``, at the patch's ``fit_level``):
    ``(x, y, theta, sigma_deg, sigma_px, scores)`` merged by their covariances (``uncertainty.merge``:
    the disagreement their covariances cannot explain carried by both), or ``None`` when the patch cannot be
    fitted there. ``scores``:
    ``patch_ncc`` (the patch's correlation at the final pose) and ``fit_chi2`` (the two fits'
    disagreement per degree of freedom; about 1 or less when they agree within their 1-sigma). ``T0``: the
    extra error each fit carries by the model's teach views (``uncertainty.merge``)."""
    Ce = cov_edge if cov_edge is not None and np.all(np.isfinite(cov_edge)) else np.diag([1e6, 1e6, 1e2])
    start = theta
    lv = min(patch.fit_level(), len(pyr) - 1)
    if math.sqrt(Ce[2, 2]) > math.radians(SCAN_SIGMA_DEG):
        # the outline barely fixes the turn (round, nearly symmetric, low contrast): the interior does
        f = 2.0 ** lv
        start = _angle_scan(patch.at_level(lv), pyr[lv], x / f, y / f, theta, scale)
    pf = _fit_at(patch, pyr, lv, x, y, start, scale)
    if pf is None or not np.all(np.isfinite(pf.cov)):
        return None
    scores = {"patch_ncc": round(pf.ncc, 4)}
    if pf.ncc < MIN_PATCH_NCC:
        return None
    pe = np.array([x, y, theta])
    pp = np.array([pf.x, pf.y, theta + math.remainder(pf.theta - theta, 2 * math.pi)])
    # a jackknife over few blocks can come out nearly singular: floor each at a thousandth px / rad^2
    eps = _COV_FLOOR
    p, C, chi = merge(pe, Ce + eps, pp, pf.cov + eps, T0)
    if chi > SPLIT_CHI2 and pf.cov[2, 2] < Ce[2, 2]:
        # the two cannot both be right (beyond 5 sigma): the edges were dragged (texture, a shading
        # gradient beside a faint outline) or never fixed the turn. The part's pixels, which match it
        # well (patch_ncc) and tell the turn more sharply, answer the turn: the patch is fitted again
        # from where it ended, and the edges' position joins it without their angle
        pf2 = _fit_at(patch, pyr, lv, pf.x, pf.y, pf.theta, pf.scale)
        if pf2 is not None and np.all(np.isfinite(pf2.cov)) and pf2.ncc >= pf.ncc:
            pf = pf2
            scores["patch_ncc"] = round(pf.ncc, 4)
        pp = np.array([pf.x, pf.y, theta + math.remainder(pf.theta - theta, 2 * math.pi)])
        Ce_pos = Ce.copy()
        Ce_pos[2, :2] = Ce_pos[:2, 2] = 0.0
        Ce_pos[2, 2] = 1e2
        p, C, _ = merge(pe, Ce_pos + eps, pp, pf.cov + eps, T0)
    sd, sp = sigma_of(C)
    scores["fit_chi2"] = round(chi, 3)
    return float(p[0]), float(p[1]), float(p[2]), sd, sp, scores


def _angle_scan(patch: TeachPatch, image: U8, x: float, y: float, theta: float, scale: float) -> float:
    """The turn (rad) at which the patch correlates best with the image at (x, y), over the whole turn
    in steps that move its outermost sample about a pixel and a half (a sparse subset of the samples,
    the image smoothed as in ``fit``); ``theta`` when nothing correlates better."""
    pts, T, _ = patch.samples()
    if len(pts) < 30:
        return theta
    sub = np.linspace(0, len(pts) - 1, min(len(pts), 800)).astype(np.int64)
    P, Tv = pts[sub], T[sub]
    r = float(np.max(np.hypot(P[:, 0], P[:, 1]))) * scale
    h, w = image.shape
    x0, y0 = max(int(x - r - 3), 0), max(int(y - r - 3), 0)
    x1, y1 = min(int(x + r + 4), w), min(int(y + r + 4), h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return theta
    crop = cv2.GaussianBlur(image[y0:y1, x0:x1].astype(np.float32), (0, 0), 2.0 * BLUR_SIGMA_PX)
    n = max(int(math.ceil(2 * math.pi * r / 1.5)), 36)
    best, best_t = -2.0, theta
    for t in theta + np.arange(n) * (2 * math.pi / n):
        q, _ = _warp(P, x - x0, y - y0, float(t), scale)
        c = _ncc(bilinear(crop, q[:, 0], q[:, 1]), Tv)
        if c > best:
            best, best_t = c, float(t)
    return best_t
