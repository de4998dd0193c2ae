"""The centre of a round part's rim, measured after a match (a metrology step, HALCON's
``fit_circle_contour_xld`` after ``find_shape_model``, in our words).

A match places the whole model: its reported point carries the edge fit's turn, and on a round part
(a screw head, a washer, a bore) the turn is barely fixed, so any offset between the model's frame
and the rim's centre swings with it. ``rim_centre`` measures the rim itself, in the channel the model
sees (``ShapeModel.colour``: the chroma of a colour image, else the grey value):

1. the model's round outline: a robust circle fit (Tukey) to its level-0 points, in the part's frame;
   refused when less than ``MIN_ROUND_SHARE`` of the points lie on it, or they do not go round it, or
   not closely (the part has no rim);
2. at the match, ``N_RAYS`` rays from the predicted centre; on each, the sub-pixel position (centroid
   of the derivative's peak, within ``REACH_PX`` of the predicted radius, or 3 of the match's 1-sigma,
   but at most ``MAX_REACH_SHARE`` of the radius) where the channel changes with the rim's polarity
   (the model's normals along the outline, dark to bright, outward or inward; or the reverse, when
   more rays show that: a part whose contrast is reversed), kept when the step reaches the model's
   contrast floor;
3. a robust circle through those points (algebraic fit, Tukey weights on the geometric residual,
   5 rounds); its 1-sigma by a block jackknife over ``N_SECTORS`` sectors of the turn (the circle
   solved again without each; neighbouring rays share the blur, the shading and the texture, which
   a per-point textbook value would take as independent).

Units: image pixels (x right, y down; centre of the top-left pixel = (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import ImageError
from vision.image import F64, bilinear
from vision.shape.colour import channel
from vision.shape.model import GRAD_PER_CONTRAST, ShapeModel
from vision.types import Match

N_RAYS = 360
N_SECTORS = 16
REACH_PX = 6.0
"""How far (px, radially) from the predicted rim the search along a ray looks, at least."""
MAX_REACH_SHARE = 0.25
"""... and at most this share of the rim's radius."""
MIN_ROUND_SHARE = 0.3
"""A model whose round outline holds fewer of its points than this has no rim to measure."""
MIN_ROUND_SECTORS = 12
"""... and they must go round it: points in this many of its ``N_SECTORS`` sectors."""
MAX_ROUND_RMS = 0.1
"""... within this RMS of the circle, as a share of its radius (an L-shaped plate: 0.29; the screw heads'
model pooled from four views: 0.03)."""
TUKEY_C = 4.685


@dataclass(frozen=True)
class RimFit:
    """The rim measured at a match (image pixels)."""

    u_px: float
    v_px: float
    radius_px: float
    sigma_px: float
    """1-sigma of the centre per axis (block jackknife over the turn's sectors)."""
    rms_px: float
    """RMS geometric residual of the inlier rim points."""
    n_points: int
    """Rim points (rays) the circle rests on (inliers)."""


def circle_fit(pts: F64, w: F64 | None = None) -> tuple[float, float, float]:
    """The weighted algebraic (Kasa) circle through ``pts`` (N, 2): centre x, y and radius."""
    w = np.ones(len(pts)) if w is None else w
    A = np.c_[2.0 * pts, np.ones(len(pts))] * w[:, None]
    b = (pts ** 2).sum(axis=1) * w
    (cx, cy, k), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(cx), float(cy), math.sqrt(max(float(k) + cx * cx + cy * cy, 0.0))


def robust_circle(pts: F64, rounds: int = 5) -> tuple[float, float, float, NDArray[np.bool_], F64]:
    """Tukey-weighted circle fit: centre x, y, radius, the inliers and the geometric residuals."""
    cx, cy, r = circle_fit(pts)
    res = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r
    w = np.ones(len(pts))
    for _ in range(rounds):
        med = float(np.median(res))  # (a first fit pulled by points off the rim sits off it by this)
        s = max(1.4826 * float(np.median(np.abs(res - med))), 0.05)
        u = (res - med) / (TUKEY_C * s)
        w = np.where(np.abs(u) < 1.0, (1.0 - u ** 2) ** 2, 0.0)
        if w.sum() < 3:
            break
        cx, cy, r = circle_fit(pts, np.sqrt(w))
        res = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r
    return cx, cy, r, w > 0, res


def model_rim(model: ShapeModel) -> tuple[float, float, float, float] | None:
    """The model's round outline in the part's frame (level-0 pixels from the ROI centre): centre x, y,
    radius, and its polarity (+1: the channel grows outward across it, -1: inward); ``None`` when
    fewer than ``MIN_ROUND_SHARE`` of the model's points lie on one circle."""
    lv = model.levels[0]
    cx, cy, r, inl, res = robust_circle(lv.points)
    radial = lv.points[inl] - (cx, cy)
    sectors = np.unique((np.arctan2(radial[:, 1], radial[:, 0]) / (2.0 * math.pi) * N_SECTORS).astype(np.int64)
                        % N_SECTORS)
    if (inl.mean() < MIN_ROUND_SHARE or r < 3.0 or len(sectors) < MIN_ROUND_SECTORS
            or math.sqrt(float((res[inl] ** 2).mean())) > MAX_ROUND_RMS * r):
        return None
    radial /= np.maximum(np.hypot(radial[:, 0], radial[:, 1]), 1e-9)[:, None]
    pol = float(np.sign(np.sum((lv.normals[inl] * radial).sum(axis=1))))
    return cx, cy, r, pol if pol != 0 else 1.0


def _rays(img: NDArray[np.float32], cx: float, cy: float, r: float, pol: float, reach: float, floor: float
          ) -> tuple[F64, F64]:
    """Sub-pixel rim points along ``N_RAYS`` rays from (cx, cy) and each ray's angle (rad)."""
    phi = np.arange(N_RAYS) * (2.0 * math.pi / N_RAYS)
    t = np.arange(max(r - reach, 1.0), r + reach + 1e-9, 0.25)
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    prof = bilinear(img, (cx + c * t[None, :]).ravel(), (cy + s * t[None, :]).ravel()).reshape(N_RAYS, len(t))
    d = pol * np.diff(prof, axis=1) / 0.25  # the rim's step, per px, positive with its polarity
    k = np.argmax(d, axis=1)
    peak = d[np.arange(N_RAYS), k]
    tm = 0.5 * (t[:-1] + t[1:])
    # the centroid of the derivative's peak (its positive part, +-1 px)
    j = np.clip(k[:, None] + np.arange(-4, 5)[None, :], 0, d.shape[1] - 1)
    seg = np.clip(np.take_along_axis(d, j, axis=1), 0.0, None)
    tot = seg.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos = np.where(tot > 0, (seg * tm[j]).sum(axis=1) / tot, tm[k])
    ok = (peak >= floor) & (k > 0) & (k < d.shape[1] - 1)
    pts = np.c_[cx + np.cos(phi) * pos, cy + np.sin(phi) * pos]
    return pts[ok], phi[ok]


def rim_centre(model: ShapeModel, image: NDArray[Any], match: Match) -> RimFit | None:
    """The rim's centre near ``match`` in ``image`` (the module), or ``None`` when the model has no round
    outline or the image shows too little of it (fewer than a quarter of the rays, or of the sectors)."""
    rim = model_rim(model)
    if rim is None:
        return None
    mx, my, r, pol = rim
    if np.asarray(image).size == 0:
        raise ImageError("the image is empty")
    a = math.radians(match.angle_deg)
    R = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    sx = -1.0 if match.mirrored else 1.0
    # the model's rim centre at the match: the match reports the model's origin
    off = match.scale * (R @ np.array([sx * (mx - model.origin[0]), my - model.origin[1]]))
    cx, cy = match.u_px + float(off[0]), match.v_px + float(off[1])
    # (never beyond a quarter of the radius: inside it lie the part's own inner edges)
    reach = min(max(REACH_PX, 3.0 * (match.sigma_px if math.isfinite(match.sigma_px) else 0.0)),
                MAX_REACH_SHARE * match.scale * r)
    # only the rim's neighbourhood is made into the channel and smoothed
    H, W = np.asarray(image).shape[:2]
    half = match.scale * r + reach + 8.0
    x0, y0 = max(int(cx - half), 0), max(int(cy - half), 0)
    x1, y1 = min(int(cx + half) + 2, W), min(int(cy + half) + 2, H)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    img = channel(np.asarray(image)[y0:y1, x0:x1], model.colour)
    f = cv2.GaussianBlur(img.astype(np.float32), (0, 0), model.params.edge_sigma_px or 1.0)
    floor = model.params.min_contrast * GRAD_PER_CONTRAST
    # the rim's polarity as taught, or reversed (the search ignores local polarity by default): the one
    # that more rays show
    found = [_rays(f, cx - x0, cy - y0, match.scale * r, sgn, reach, floor) for sgn in (pol, -pol)]
    pts, phi = max(found, key=lambda pf: len(pf[0]))
    pts = pts + (x0, y0)
    if len(pts) < N_RAYS // 4:
        return None
    ux, uy, rr, inl, res = robust_circle(pts)
    sector = (phi / (2.0 * math.pi) * N_SECTORS).astype(np.int64) % N_SECTORS
    present = [k for k in range(N_SECTORS) if np.any(inl & (sector == k))]
    if len(present) < N_SECTORS // 4:
        return None
    js = []
    for k in present:  # the block jackknife: the circle again without sector k's points
        keep = inl & (sector != k)
        if keep.sum() >= 3:
            js.append(circle_fit(pts[keep])[:2])
    J = np.array(js)
    n = len(J)
    var = (n - 1) / n * ((J - J.mean(axis=0)) ** 2).sum(axis=0)
    rms = math.sqrt(float((res[inl] ** 2).mean()))
    return RimFit(ux, uy, rr, math.sqrt(float(var.mean())), rms, int(inl.sum()))
