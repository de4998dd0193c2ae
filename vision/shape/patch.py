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

``uncertainty.combine`` merges the edge fit and the patch fit by their covariances and widens the result by their
disagreement (a chi-square over its degrees of freedom): a pose the two methods disagree on says so
in its 1-sigma. Units: pixels of the image (level 0), angles in radians inside, degrees in ``Match``.
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
from vision.shape.uncertainty import combine, honest_cov, sigma_of

MAX_SAMPLES = 6000
"""Sample points of a patch (a large part is subsampled on a grid: its fit's cost is bounded)."""
TUKEY_C = 4.685
"""Tukey's biweight constant (in robust standard deviations of the residual)."""
BLUR_SIGMA_PX = 1.0
"""Patch and image are smoothed alike before the fit: bilinear interpolation of a sharp image pulls a
grey-value fit towards whole pixels (a few hundredths of a pixel on rendered edges); smoothed, it does
not."""
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
        iterations: int = 12, fit_scale: bool = True) -> PatchFit | None:
    """Align the patch to ``image`` from the pose (x, y, theta, scale); ``None`` when too little of it
    lies inside the image or the fit runs away (more than the part's size from the start)."""
    pts, T, tmag = patch.samples()
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
    p = np.array([x - x0, y - y0, theta, scale])
    start = p.copy()
    nparam = 4 if fit_scale else 3
    wgt = np.ones(len(pts))
    converged = False
    J = r = np.zeros(0)
    inside = np.zeros(len(pts), bool)
    for _ in range(iterations):
        q, dth = _warp(pts, *p)
        inside = (q[:, 0] >= 1) & (q[:, 1] >= 1) & (q[:, 0] <= x1 - x0 - 2) & (q[:, 1] <= y1 - y0 - 2)
        if inside.sum() < 0.5 * len(pts):
            return None
        I = bilinear(crop, q[:, 0], q[:, 1])
        Ix, Iy = bilinear(gx, q[:, 0], q[:, 1]), bilinear(gy, q[:, 0], q[:, 1])
        # the light: T ~ a I + b (weighted least squares at this pose)
        ww = wgt * inside
        A = np.stack([I, np.ones_like(I)], axis=1)
        ab = np.linalg.lstsq(A * ww[:, None], T * ww, rcond=None)[0]
        a = float(ab[0]) if abs(ab[0]) > 1e-6 else 1e-6
        r = a * I + ab[1] - T
        # robust weights: Tukey on the residual's robust spread
        sd = 1.4826 * float(np.median(np.abs(r[inside]))) + 1e-6
        u2 = (r / (TUKEY_C * sd)) ** 2
        wgt = np.where((u2 < 1) & inside, (1 - u2) ** 2, 0.0)
        cols = [a * Ix, a * Iy, a * (Ix * dth[:, 0] + Iy * dth[:, 1])]
        if fit_scale:
            dsc = (q - p[:2]) / p[3]
            cols.append(a * (Ix * dsc[:, 0] + Iy * dsc[:, 1]))
        J = np.stack(cols + [I, np.ones_like(I)], axis=1)
        H = J.T @ (J * wgt[:, None])
        g = J.T @ (wgt * r)
        try:
            d = -np.linalg.solve(H + 1e-9 * np.eye(len(H)) * np.trace(H), g)
        except np.linalg.LinAlgError:
            return None
        p[:nparam] += d[:nparam]
        if fit_scale:
            p[3] = float(np.clip(p[3], 0.5 * scale, 1.5 * scale))
        if math.hypot(p[0] - start[0], p[1] - start[1]) > r_max:
            return None
        if abs(d[0]) + abs(d[1]) < 1e-3 and abs(d[2]) * r_max < 1e-3:
            converged = True
            break
    q, _ = _warp(pts, *p)
    I = bilinear(crop, q[:, 0], q[:, 1])
    ok = inside & (wgt > 0)
    ncc = _ncc(I[inside], T[inside])
    # samples closer than the blur's reach share their errors: samples per independent one
    step = float(np.median(np.hypot(*np.diff(pts[: min(len(pts), 200)], axis=0).T))) if len(pts) > 2 else 1.0
    cov = honest_cov(pts, J, r, wgt, max((2.0 * BLUR_SIGMA_PX / max(min(step, 4.0), 0.5)) ** 2, 1.0))
    return PatchFit(float(p[0] + x0), float(p[1] + y0), float(p[2]), float(p[3]), ncc, cov, int(ok.sum()),
                    converged)


def _ncc(a: F64, b: F64) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else 0.0


SCAN_SIGMA_DEG = 1.0
"""Where the edge fit's angle 1-sigma exceeds this, the patch's correlation is scanned over the whole
turn first (``_angle_scan``): the outline does not fix the angle, the interior may."""
MIN_PATCH_NCC = 0.5
"""A patch fit correlating less than this with the image is not used (a part seen under another light
or much hidden: the edge fit alone answers, its own 1-sigma stands)."""


def finish(patch: TeachPatch, image: U8, x: float, y: float, theta: float, scale: float,
           cov_edge: F64 | None) -> tuple[float, float, float, float, float, dict[str, float]] | None:
    """The final pose from the edge fit's ``(x, y, theta, scale)`` (level-0 px, rad) and its covariance,
    and the patch fit from there: ``(x, y, theta, sigma_deg, sigma_px, scores)`` merged by their
    covariances (``uncertainty.combine``: widened by their disagreement), or ``None`` when the patch
    cannot be fitted there. ``scores``: ``patch_ncc`` (the patch's correlation at the final pose) and
    ``fit_chi2`` (the two fits' disagreement per degree of freedom; about 1 or less when they agree
    within their 1-sigma)."""
    sd_edge = math.sqrt(cov_edge[2, 2]) if cov_edge is not None and np.isfinite(cov_edge[2, 2]) else math.inf
    if sd_edge > math.radians(SCAN_SIGMA_DEG):
        # the outline barely fixes the turn (round, nearly symmetric, low contrast): the interior does
        theta = _angle_scan(patch, image, x, y, theta, scale)
    pf = fit(patch, image, x, y, theta, scale)
    if pf is None or not np.all(np.isfinite(pf.cov)):
        return None
    scores = {"patch_ncc": round(pf.ncc, 4)}
    if pf.ncc < MIN_PATCH_NCC:
        return None
    pe = np.array([x, y, theta])
    pp = np.array([pf.x, pf.y, theta + math.remainder(pf.theta - theta, 2 * math.pi)])
    Ce = cov_edge if cov_edge is not None and np.all(np.isfinite(cov_edge)) else np.diag([1e6, 1e6, 1e2])
    # a jackknife over few blocks can come out nearly singular: floor each at a thousandth px / rad^2
    eps = np.diag([1e-6, 1e-6, 1e-10])
    p, C, chi = combine(pe, Ce + eps, pp, pf.cov + eps)
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
