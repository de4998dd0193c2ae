"""Shape-based matching: find a taught part at any rotation, to a fraction of a pixel and degree.

The model is a set of edge points with their gradient directions, taken from the teach image's
ROI on every level of an image pyramid (``cv2.pyrDown``: level-``l`` pixel ``x`` lies at
level-0 ``2**l * x``); the ROI centre is the reference point. Matching ignores edge polarity
(orientations modulo 180°), so contrast reversal and uneven light do not matter; only a minimum
edge contrast does.

Search, coarse to fine:

1. **Top level, exhaustive** (line2Dup / LINE-MOD style): the image's gradient orientation is
   quantized into 8 bins over 180°; per bin a response map (0..4 by orientation difference,
   through ``cv2.LUT``), spread by a 3x3 max filter. A rotated template's score map is the sum
   of its features' response maps shifted by the rotated feature offsets — one vectorised
   ``uint8`` add per feature and angle, all positions at once. Angle step ``1.8/r`` (r: model
   radius at that level). Local maxima over position *and* angle, so several angle hypotheses
   of a nearly symmetric part survive.
2. **Tracking down the pyramid** (batched gathers): on the level below the top, +-2 angle steps
   and +-2 px on spread responses; on each finer level +-1; on the last discrete level a second
   pass on unspread responses settles the +-1 px plateaus the spreading leaves.
3. **Least-squares refinement** on level 1, then level 0: each model edge point is moved along
   its (rotated) normal to the nearest image edge of matching orientation (peak of the gradient
   component along the normal, sub-pixel by a Gaussian fit), and Gauss-Newton on (u, v, angle,
   scale) minimises the squared normal distances with Tukey weights (occlusion and clutter get
   weight 0). On level 0 the edge positions are then taken as the centroid of the intensity
   profile's differences along the normal — exact for a step edge whatever its sub-pixel phase,
   where a peak fit aliases by a few hundredths of a pixel — and the fit ends with a plane
   homography (a slightly tilted camera's perspective), whose local linear map at the reference
   point gives the angle and scale.

The score is the mean over model points of ``|cos|`` of the orientation difference times a
distance weight at the final pose — the fraction of the model's edges that are seen where they
should be, so it falls smoothly with occlusion. Matches closer than a third of the ROI's smaller
side, or whose model rectangles overlap a better match by more than ``max_overlap``, are dropped.

Own code over OpenCV primitives: OpenCV has no rotation-invariant shape matcher with sub-pixel
refinement (``matchTemplate`` is translation-only, ``matchShapes`` gives no pose).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

N_BINS = 8
_BIN_W = math.pi / N_BINS
TOP_STEP_FACTOR = 1.8
"""Top-level angle step in units of 1/r: the outermost feature moves <= 0.7 px off a step."""
MIN_TOP_RADIUS_PX = 8.0
"""Automatic pyramid depth: the top level must show the model at least this large."""
MAX_TOP_CANDIDATES = 64
HYPOTHESES_PER_POSITION = 3
_TRACE: list[tuple[str, int, list[tuple[float, float, float, float]]]] | None = None
"""Set to a list to record the candidates of each stage (diagnostics)."""
TOP_STRIDE = 1
"""Top-level positions are scored on a grid of this stride (responses spread to match)."""
PERSPECTIVE_DEFAULT = True
MAX_TOP_FEATURES = 24  # 4 * 63 < 256: uint8 accumulators cannot overflow (keep <= 63)
MAX_TRACK_FEATURES = 64
MAX_FINE_POINTS = 240
GRAD_PER_CONTRAST = 0.25  # peak gradient (grey/px) of a blurred step of unit contrast, roughly


@dataclass(frozen=True)
class TeachParams:
    """How the model was taught (stored in the model file)."""

    min_contrast: float = 12.0
    """Minimum grey-value step of an edge (teach and find)."""
    num_levels: int = 0
    """Pyramid levels (0 = automatic from the ROI size)."""
    edge_sigma_px: float = 1.0
    """Gaussian smoothing before the level-0 gradients."""

    def to_dict(self) -> dict[str, Any]:
        return {"min_contrast": self.min_contrast, "num_levels": self.num_levels,
                "edge_sigma_px": self.edge_sigma_px}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TeachParams:
        return cls(float(d.get("min_contrast", 12.0)), int(d.get("num_levels", 0)),
                   float(d.get("edge_sigma_px", 1.0)))


@dataclass
class LevelModel:
    """Edge points of one pyramid level, relative to the reference point (level pixels)."""

    level: int
    points: F64
    """(N, 2) sub-pixel edge points."""
    normals: F64
    """(N, 2) unit gradient directions (sign irrelevant)."""
    features: NDArray[np.int64]
    """Indices of the points used for the discrete search on this level."""

    @property
    def radius(self) -> float:
        r = self.__dict__.get("_radius")
        if r is None:
            r = float(np.max(np.hypot(self.points[:, 0], self.points[:, 1])))
            self.__dict__["_radius"] = r
        return r

    @property
    def angle_step(self) -> float:
        """Angle step (rad) of the discrete tracking: the outermost point moves <= 1 px."""
        return 1.0 / max(self.radius, 2.0)

    def to_dict(self) -> dict[str, Any]:
        phi = np.degrees(np.arctan2(self.normals[:, 1], self.normals[:, 0]))
        return {"level": self.level,
                "points": [[round(float(x), 4), round(float(y), 4), round(float(a), 3)]
                           for (x, y), a in zip(self.points, phi, strict=True)],
                "features": [int(i) for i in self.features]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LevelModel:
        arr = np.asarray(d["points"], dtype=np.float64).reshape(-1, 3)
        a = np.radians(arr[:, 2])
        feats = np.asarray(d["features"], dtype=np.int64)
        if len(arr) < 3 or len(feats) == 0 or feats.max() >= len(arr) or feats.min() < 0:
            raise ValueError(f"model level {d.get('level')} is corrupt (too few points or bad indices)")
        return cls(int(d["level"]), arr[:, :2].copy(), np.stack([np.cos(a), np.sin(a)], axis=1), feats)


@dataclass
class ShapeModel:
    """A taught shape model: one ``LevelModel`` per pyramid level (index = level)."""

    levels: list[LevelModel]
    params: TeachParams
    roi: tuple[float, float, float, float]
    image_size: tuple[int, int]

    @property
    def top_level(self) -> int:
        return len(self.levels) - 1

    def to_dict(self) -> dict[str, Any]:
        return {"levels": [lv.to_dict() for lv in self.levels]}

    @classmethod
    def from_dict(cls, d: dict[str, Any], params: TeachParams, roi: tuple[float, float, float, float],
                  image_size: tuple[int, int]) -> ShapeModel:
        return cls([LevelModel.from_dict(x) for x in d["levels"]], params, roi, image_size)


@dataclass(frozen=True)
class SearchParams:
    """Bounds of one search."""

    min_score: float = 0.5
    max_count: int = 0
    """Most matches to return (0: all)."""
    angle_start_deg: float = -180.0
    angle_extent_deg: float = 360.0
    roi: tuple[float, float, float, float] | None = None
    """Search region ``(U, V, W, H)`` for the reference point; ``None``: the whole image."""
    timeout_s: float | None = None
    min_distance_px: float | None = None
    """Two matches closer than this are one (default: a third of the model's smaller size)."""
    max_overlap: float = 0.5
    """A match whose model rectangle overlaps a better one's by more than this fraction is dropped."""
    max_scale_dev: float = 0.1
    """The final fit may scale the model by up to this fraction (a slightly tilted view); 0: rigid."""
    perspective: bool = PERSPECTIVE_DEFAULT
    """Finish with a plane-homography fit (a tilted camera): the reference point and angle are then
    those of the part's plane seen in perspective."""


@dataclass
class Match:
    u_px: float
    v_px: float
    angle_deg: float
    score: float
    rms_px: float = float("nan")
    """RMS normal distance of the inlier model edge points after refinement."""
    scale: float = 1.0
    """Apparent size relative to the teach image (a tilted view), from the final fit."""

    def as_dict(self) -> dict[str, float]:
        return {"u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg, "score": self.score,
                "scale": self.scale}


@dataclass
class FindResult:
    matches: list[Match]
    timed_out: bool = False
    elapsed_s: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- image helpers


def as_gray(image: NDArray[Any]) -> U8:
    """A single-channel uint8 view of ``image`` (BGR is converted)."""
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


def _gauss_peak(gm: F64, g0: F64, gp: F64) -> F64:
    """Sub-sample peak offset of three positive samples by a Gaussian (log-parabola) fit."""
    lm, l0, lp = np.log(np.maximum(gm, 1e-6)), np.log(np.maximum(g0, 1e-6)), np.log(np.maximum(gp, 1e-6))
    den = lm - 2 * l0 + lp
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < -1e-9, 0.5 * (lm - lp) / den, 0.0)
    return np.clip(off, -0.5, 0.5)


CENTROID_HALF_WIDTH = 3


def _centroid(img: F32, q: F64, n: F64, half_width: int = CENTROID_HALF_WIDTH
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


# ----------------------------------------------------------------------------- teach


def _edge_points(img: U8, sigma: float, thr: float, box: tuple[float, float, float, float]
                 ) -> tuple[F64, F64, F64]:
    """Sub-pixel edge points (x, y), unit normals and magnitudes inside ``box`` (x0, y0, x1, y1)."""
    h, w = img.shape
    x0, y0, x1, y1 = box
    m = 4 + int(math.ceil(3 * sigma))
    cx0, cy0 = max(int(math.floor(x0)) - m, 0), max(int(math.floor(y0)) - m, 0)
    cx1, cy1 = min(int(math.ceil(x1)) + m, w - 1), min(int(math.ceil(y1)) + m, h - 1)
    crop = img[cy0:cy1 + 1, cx0:cx1 + 1]
    gx, gy = gradients(crop, sigma)
    mag = cv2.magnitude(gx, gy)
    ys, xs = np.nonzero(mag >= thr)
    keep = (xs >= 1) & (ys >= 1) & (xs < mag.shape[1] - 1) & (ys < mag.shape[0] - 1)
    xs, ys = xs[keep].astype(np.float64), ys[keep].astype(np.float64)
    g = mag[ys.astype(np.int64), xs.astype(np.int64)].astype(np.float64)
    nx = gx[ys.astype(np.int64), xs.astype(np.int64)] / g
    ny = gy[ys.astype(np.int64), xs.astype(np.int64)] / g

    def along(t: float) -> F64:
        return np.abs(bilinear(gx, xs + t * nx, ys + t * ny) * nx + bilinear(gy, xs + t * nx, ys + t * ny) * ny)

    gm, g0, gp = along(-1.0), along(0.0), along(1.0)
    is_max = (g0 >= gm) & (g0 > gp)
    off = _gauss_peak(gm, g0, gp)
    px = xs + off * nx + cx0
    py = ys + off * ny + cy0
    inside = is_max & (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)
    return (np.stack([px[inside], py[inside]], axis=1), np.stack([nx[inside], ny[inside]], axis=1),
            g0[inside])


def _profile_ok(img: F32, q: F64, n: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Centroid offsets, contrasts and whether each profile is one clean monotonic step."""
    off, S, D = _centroid(img, q, n)
    wrong = np.clip(-D * np.sign(S)[:, None], 0, None).sum(axis=1)
    clean = wrong <= 0.1 * np.abs(S)
    return off, S, clean


def _centroid_refine(img: U8, pts: F64, nrm: F64, mag: F64, min_contrast: float
                     ) -> tuple[F64, F64, F64]:
    """Move level-0 edge points to the centroid edge position; drop corners and cramped edges."""
    f = img.astype(np.float32)
    off, S, clean = _profile_ok(f, pts, nrm)
    keep = clean & (np.abs(off) < 0.75) & (np.abs(S) >= 0.5 * min_contrast)
    pts = pts + off[:, None] * nrm
    return pts[keep], nrm[keep], mag[keep]


def _spread_subset(pts: F64, strength: F64, target: int, min_spacing: float) -> NDArray[np.int64]:
    """Indices of at most ``target`` points, strongest first, no two closer than a spacing."""
    order = np.argsort(-strength, kind="stable")
    spacing = min_spacing
    while True:
        cell = spacing / math.sqrt(2.0)
        taken: dict[tuple[int, int], int] = {}
        chosen: list[int] = []
        keys = np.floor(pts / cell).astype(np.int64)
        r = int(math.ceil(spacing / cell))
        for i in order:
            kx, ky = int(keys[i, 0]), int(keys[i, 1])
            ok = True
            for dx in range(-r, r + 1):
                for dy in range(-r, r + 1):
                    j = taken.get((kx + dx, ky + dy))
                    if j is not None and (pts[j, 0] - pts[i, 0]) ** 2 + (pts[j, 1] - pts[i, 1]) ** 2 \
                            < spacing * spacing:
                        ok = False
                        break
                if not ok:
                    break
            if ok:
                taken[(kx, ky)] = int(i)
                chosen.append(int(i))
        if len(chosen) <= target:
            return np.asarray(sorted(chosen), dtype=np.int64)
        spacing *= 1.15


def auto_levels(roi_w: float, roi_h: float) -> int:
    """Pyramid levels so the top level shows the ROI's smaller side at >= 8 px (at most 5).

    ``teach`` then drops top levels where the model is too thin (see ``MIN_TOP_RADIUS_PX``).
    """
    n = 1
    while n < 5 and min(roi_w, roi_h) / 2 ** n >= 8.0:
        n += 1
    return n


def teach(image: NDArray[Any], roi: tuple[float, float, float, float],
          params: TeachParams | None = None) -> ShapeModel:
    """Teach a shape model from the ROI ``(U, V, W, H)``; its centre is the reference point."""
    p = params or TeachParams()
    img = as_gray(image)
    u, v, w, h = roi
    ref = np.array([u + w / 2.0, v + h / 2.0])
    n_levels = p.num_levels if p.num_levels > 0 else auto_levels(w, h)
    pyr = pyramid(img, n_levels)
    levels: list[LevelModel] = []
    for lv, im in enumerate(pyr):
        s = 2.0 ** lv
        sigma = p.edge_sigma_px if lv == 0 else 0.0
        pts, nrm, mag = _edge_points(im, sigma, p.min_contrast * GRAD_PER_CONTRAST,
                                     (u / s, v / s, (u + w) / s, (v + h) / s))
        if len(pts) < 8:
            if lv == 0:
                raise ValueError(
                    f"no edges of contrast >= {p.min_contrast:g} in the ROI: choose a region that "
                    "shows the part, or lower the minimum contrast")
            break
        if lv == 0:
            pts, nrm, mag = _centroid_refine(img, pts, nrm, mag, p.min_contrast)
            if len(pts) < 8:
                raise ValueError("too few clean edges in the ROI: choose a region that shows the part")
        pts = pts - ref / s
        if lv == 0:
            sel = _spread_subset(pts, mag, MAX_FINE_POINTS, 2.0)
            pts, nrm, mag = pts[sel], nrm[sel], mag[sel]
            feats = np.arange(len(pts), dtype=np.int64)
        else:
            sel = _spread_subset(pts, mag, 4 * MAX_TRACK_FEATURES, 1.0)
            pts, nrm, mag = pts[sel], nrm[sel], mag[sel]
            feats = _spread_subset(pts, mag, MAX_TRACK_FEATURES, 1.5)
        levels.append(LevelModel(lv, pts, nrm, feats))
    # the top level is searched exhaustively: fewer, well spread features; drop levels that are too thin
    while len(levels) > 1 and (len(levels[-1].points) < 16 or levels[-1].radius < MIN_TOP_RADIUS_PX):
        levels.pop()
    top = levels[-1]
    top.features = _spread_subset(top.points, np.ones(len(top.points)), MAX_TOP_FEATURES, 1.5) \
        if top.level > 0 else top.features[:MAX_TOP_FEATURES]
    return ShapeModel(levels, p, (u, v, w, h), (img.shape[1], img.shape[0]))


# ----------------------------------------------------------------------------- responses


def _response_table() -> U8:
    """(N_BINS, 4*N_BINS+1) responses of each feature bin to each quarter-bin orientation."""
    t = np.zeros((N_BINS, 4 * N_BINS + 1), np.uint8)  # last column: no edge
    for b in range(N_BINS):
        for qb in range(4 * N_BINS):
            d = abs(qb + 0.5 - (4.0 * b + 2.0))
            d = min(d, 4.0 * N_BINS - d)  # circular distance in quarter-bins (1 = 5.625 deg)
            t[b, qb] = int(np.clip(4 - math.floor(d * 0.5), 0, 4))  # 4 within ~11 deg, 0 beyond 45
    return t


_RESPONSE_TABLE = _response_table()
_RESPONSE_LUT = np.zeros((N_BINS, 1, 256), np.uint8)
_RESPONSE_LUT[:, 0, :4 * N_BINS + 1] = _RESPONSE_TABLE


def response_maps(img: U8, thr: float, sigma: float = 0.0, spread: int = 3) -> U8:
    """(N_BINS, H, W) uint8 responses 0..4 to each orientation bin, spread by a max filter.

    ``spread`` is the max filter's size (1: none).
    """
    gx, gy = gradients(img, sigma)
    mag = cv2.magnitude(gx, gy)
    ang = cv2.phase(gx, gy, angleInDegrees=True)  # 0..360
    q = cv2.convertScaleAbs(ang, alpha=4.0 * N_BINS / 180.0, beta=-0.5)  # floor: quarter-bins 0..63
    q = cv2.bitwise_and(q, 4 * N_BINS - 1)  # orientation modulo 180 deg
    q[mag < thr] = 4 * N_BINS
    h, w = img.shape
    out = np.empty((N_BINS, h, w), np.uint8)
    for b in range(N_BINS):
        cv2.LUT(q, _RESPONSE_LUT[b], dst=out[b])
    return _spread(out, spread)


def _spread(resp: U8, size: int) -> U8:
    """Max filter of each bin's responses (``size`` x ``size``; 1 returns ``resp``)."""
    if size <= 1:
        return resp
    nb, h, w = resp.shape
    stack = np.zeros((nb, h + size // 2, w), np.uint8)  # zero rows between bins keep them apart
    stack[:, :h] = resp
    flat = cv2.dilate(stack.reshape(nb * (h + size // 2), w), np.ones((size, size), np.uint8))
    return np.ascontiguousarray(flat.reshape(nb, h + size // 2, w)[:, :h])


def _rotated_features(lm: LevelModel, thetas: F64) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                            NDArray[np.int64]]:
    """Rounded feature offsets (A, F) dx, dy and orientation bins for each angle."""
    m = lm.points[lm.features]
    n = lm.normals[lm.features]
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    dx = np.rint(c * m[:, 0] + s * m[:, 1]).astype(np.int64)
    dy = np.rint(-s * m[:, 0] + c * m[:, 1]).astype(np.int64)
    phi = np.arctan2(n[:, 1], n[:, 0])[None, :] - thetas[:, None]
    b = (np.floor(np.mod(phi, math.pi) / _BIN_W).astype(np.int64)) % N_BINS
    return dx, dy, b


def _track(resp: U8, lm: LevelModel, cx: NDArray[np.int64], cy: NDArray[np.int64], th: F64,
           n_steps: int = 1, reach: int = 1) -> tuple[F64, F64, F64, F64]:
    """Best pose of each candidate over +-reach px and +-n_steps angle steps: (x, y, theta, score).

    With the responses spread over 3x3, reach 1 covers a candidate that is up to 2 px off.
    """
    da = lm.angle_step
    m = lm.points[lm.features]
    n = lm.normals[lm.features]
    nf = len(m)
    na = 2 * n_steps + 1
    thetas = th[:, None] + (np.arange(na) - n_steps)[None, :] * da  # (C, na)
    c, s = np.cos(thetas)[..., None], np.sin(thetas)[..., None]
    dx = np.rint(c * m[:, 0] + s * m[:, 1]).astype(np.int32)  # (C, A, F)
    dy = np.rint(-s * m[:, 0] + c * m[:, 1]).astype(np.int32)
    phi = np.arctan2(n[:, 1], n[:, 0]) - thetas[..., None]
    b = (np.floor(np.mod(phi, math.pi) / _BIN_W).astype(np.int32)) % N_BINS
    _, h, w = resp.shape
    P = int(math.ceil(lm.radius)) + reach + 2  # zero border: no bounds checks in the gather
    padded = np.zeros((N_BINS, h + 2 * P, w + 2 * P), np.uint8)
    padded[:, P:P + h, P:P + w] = resp
    hp, wp = h + 2 * P, w + 2 * P
    cx = np.clip(cx, 0, w - 1)
    cy = np.clip(cy, 0, h - 1)
    offs = np.arange(-reach, reach + 1)
    npos = len(offs) ** 2
    ox = np.tile(offs, len(offs))
    oy = np.repeat(offs, len(offs))
    base = ((cy + P) * wp + cx + P).astype(np.int32)
    pos = (oy * wp + ox).astype(np.int32)
    feat = b * (hp * wp) + dy * wp + dx  # (C, A, F)
    idx = base[:, None, None, None] + pos[None, None, :, None] + feat[:, :, None, :]  # (C, A, P, F)
    sc = padded.ravel()[idx].sum(axis=3, dtype=np.int32).reshape(len(cx), -1)
    # ties (the spread responses make plateaus) go to the angle nearest the prediction, and the
    # position is the plateau's centre rather than its first pixel
    tie = np.abs(np.arange(na) - n_steps).repeat(npos) * 0.01
    k = np.argmax(sc - tie[None, :], axis=1)
    ai = k // npos
    rows = np.arange(len(cx))
    best = sc[rows, k]
    at_a = sc.reshape(len(cx), na, npos)[rows, ai]  # (C, npos)
    plateau = at_a == best[:, None]
    cnt = plateau.sum(axis=1)
    px = (plateau * ox[None, :]).sum(axis=1) / cnt
    py = (plateau * oy[None, :]).sum(axis=1) / cnt
    return cx + px, cy + py, thetas[rows, ai], best / (4.0 * nf)


# ----------------------------------------------------------------------------- refinement


@dataclass
class _Pose:
    x: float
    y: float
    theta: float  # rad
    score: float
    scale: float = 1.0


def _gn_step(n: F64, Rm: F64, Rdm: F64, scale: float, wgt: F64, resid: F64, fit_scale: bool) -> F64:
    """One weighted Gauss-Newton step for (x, y, theta[, scale]) on normal distances."""
    cols = [n[:, 0], n[:, 1], scale * np.sum(n * Rdm, axis=1)]
    if fit_scale:
        cols.append(np.sum(n * Rm, axis=1))
    J = np.stack(cols, axis=1)
    A = J.T @ (J * wgt[:, None]) + np.eye(J.shape[1]) * 1e-9
    delta = np.linalg.solve(A, J.T @ (wgt * resid))
    return np.asarray(delta if fit_scale else np.append(delta, 0.0), dtype=np.float64)


def _associate(G: F32, q: F64, n: F64, reach: float, thr: float) -> tuple[F64, NDArray[np.bool_], F64]:
    """Nearest image edge of matching orientation along each normal within ``reach`` px.

    Returns the signed distances (sub-pixel, Gaussian fit of the gradient component along the
    normal), whether an edge was found, and ``|cos|`` of the orientation difference there.
    """
    npts = len(q)
    rows = np.arange(npts)
    ts = np.arange(-math.ceil(reach), math.ceil(reach) + 1, dtype=np.float64)
    k = len(ts)
    sx = q[:, 0:1] + ts[None, :] * n[:, 0:1]
    sy = q[:, 1:2] + ts[None, :] * n[:, 1:2]
    gxy = bilinear2(G, sx.ravel(), sy.ravel()).reshape(npts, k, 2)
    gn = np.abs(gxy[..., 0] * n[:, 0:1] + gxy[..., 1] * n[:, 1:2])
    gm2 = gxy[..., 0] ** 2 + gxy[..., 1] ** 2
    good = (gn >= thr) & (gn * gn >= 0.81 * gm2)
    g = np.where(good, gn, 0.0)
    locmax = np.zeros_like(good)
    locmax[:, 1:-1] = good[:, 1:-1] & (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] > g[:, 2:])
    cost = np.where(locmax, np.abs(ts)[None, :], np.inf)
    j = np.argmin(cost, axis=1)
    found = locmax[rows, j]
    jj = np.minimum(np.maximum(j, 1), k - 2)
    off = _gauss_peak(g[rows, jj - 1], g[rows, jj], g[rows, jj + 1])
    d = np.where(found, ts[jj] + off, 0.0)
    cosd = np.where(found, gn[rows, jj] / np.sqrt(np.maximum(gm2[rows, jj], 1e-12)), 0.0)
    return d, found, cosd


def _refine_lsq(img_level: U8, lm: LevelModel, pose: _Pose, sigma: float, thr: float,
                search_px: float, iterations: int, fine: U8 | None = None,
                min_contrast: float = 0.0, subset: NDArray[np.int64] | None = None,
                reject_below: float = 0.0, fit_scale: bool = False,
                max_scale_dev: float = 0.1, perspective: bool = False) -> tuple[_Pose, float, float]:
    """Gauss-Newton fit of the model edge points to the image edges; returns (pose, score, rms).

    With ``fit_scale`` the fit is a similarity (a slightly tilted view makes the part look a few
    per cent larger or smaller; a rigid fit would turn that into a position error).
    """
    m = lm.points if subset is None else lm.points[subset]
    nrm_m = lm.normals if subset is None else lm.normals[subset]
    npts = len(m)
    dm0 = np.stack([m[:, 1], -m[:, 0]], axis=1)  # d(R m)/d theta = R (m_y, -m_x)
    reach = lm.radius * (1 + max_scale_dev) + search_px + 5 + 3 * sigma
    h, w = img_level.shape
    x0, y0 = max(int(pose.x - reach), 0), max(int(pose.y - reach), 0)
    x1, y1 = min(int(pose.x + reach) + 1, w - 1), min(int(pose.y + reach) + 1, h - 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return pose, 0.0, float("nan")
    gx, gy = gradients(img_level[y0:y1 + 1, x0:x1 + 1], sigma)
    G = cv2.merge([gx, gy])
    x, y, th, sc = pose.x - x0, pose.y - y0, pose.theta, pose.scale
    rng = search_px
    d = np.zeros(npts)
    found = np.zeros(npts, bool)
    cosd = np.zeros(npts)

    def update(delta: F64) -> float:
        nonlocal x, y, th, sc
        x += float(delta[0])
        y += float(delta[1])
        th += float(delta[2])
        sc = float(np.clip(sc + float(delta[3]), 1 - max_scale_dev, 1 + max_scale_dev))
        return abs(float(delta[0])) + abs(float(delta[1])) + (abs(float(delta[2])) + abs(float(delta[3]))) \
            * lm.radius

    for it in range(iterations):
        R = rot(th)
        Rm = m @ R.T
        q = sc * Rm + np.array([x, y])
        n = nrm_m @ R.T
        d, found, cosd = _associate(G, q, n, rng, thr)
        # Tukey weights on the normal distances
        c = max(rng * 0.75, 1.0)
        wgt = np.where(found & (np.abs(d) < c), (1 - (d / c) ** 2) ** 2, 0.0)
        if wgt.sum() < 6 or (it == 0 and np.count_nonzero(found) < reject_below * npts):
            return _Pose(x + x0, y + y0, th, 0.0, sc), 0.0, float("nan")
        moved = update(_gn_step(n, Rm, dm0 @ R.T, sc, wgt, d, fit_scale and (it > 0 or iterations == 1)))
        rng = max(rng * 0.6, 1.5)
        if moved < 0.02:
            break
    if fine is not None:
        # stage B: centroid edge positions on the raw image (phase-exact), a few Gauss-Newton steps
        img_f = fine[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
        sel = found & (np.abs(d) < 1.0)
        ms, ns, dms = m[sel], nrm_m[sel], dm0[sel]
        for _ in range(1 if perspective else 3):
            R = rot(th)
            Rm = ms @ R.T
            q = sc * Rm + np.array([x, y])
            n = ns @ R.T
            off, S, clean = _profile_ok(img_f, q, n)
            ok = clean & (np.abs(off) < 1.0) & (np.abs(S) >= 0.5 * min_contrast)
            wgt = np.where(ok, (1 - off ** 2) ** 2, 0.0)
            if wgt.sum() < 6:
                break
            if update(_gn_step(n, Rm, dms @ R.T, sc, wgt, off, fit_scale)) < 1e-3:
                break
        if perspective:
            x, y, th, sc = _perspective_fit(img_f, ms, ns, x, y, th, sc, min_contrast)
        # the score is taken at the final pose
        R = rot(th)
        q = sc * (m @ R.T) + np.array([x, y])
        n = nrm_m @ R.T
        d, found, cosd = _associate(G, q, n, 2.0, thr)
    s_i = np.where(found, cosd * np.clip(1.0 - (d / 1.5) ** 2, 0.0, 1.0), 0.0)
    inl = found & (np.abs(d) < 1.0)
    rms = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan")
    return _Pose(x + x0, y + y0, th, float(s_i.mean()), sc), float(s_i.mean()), rms


def _perspective_fit(img_f: F32, m: F64, nrm: F64, x: float, y: float, th: float, sc: float,
                     min_contrast: float) -> tuple[float, float, float, float]:
    """Refine a similarity to a plane homography of the model (a tilted camera's view).

    ``q = (A m + c) / (1 + p.m)``; the reference point is ``c`` and the reported angle and scale
    are those of the local linear map ``A - c p^T`` at the reference point (the direction the
    part's x axis takes there). Gauss-Newton on the centroid normal distances.
    """
    R = rot(th)
    A = sc * R
    c = np.array([x, y])
    pv = np.zeros(2)
    for _ in range(2):
        w = 1.0 + m @ pv
        q = (m @ A.T + c) / w[:, None]
        J_lin = A - np.outer(c, pv)
        n = nrm @ J_lin.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        off, S, clean = _profile_ok(img_f, q, n)
        ok = clean & (np.abs(off) < 1.0) & (np.abs(S) >= 0.5 * min_contrast)
        wgt = np.where(ok, (1 - off ** 2) ** 2, 0.0)
        if np.count_nonzero(wgt) < 20:
            break
        mx, my = m[:, 0] / w, m[:, 1] / w
        inv = 1.0 / w
        nx, ny = n[:, 0], n[:, 1]
        qn = nx * q[:, 0] + ny * q[:, 1]
        J = np.stack([nx * mx, nx * my, nx * inv, ny * mx, ny * my, ny * inv, -qn * mx, -qn * my], axis=1)
        Hm = J.T @ (J * wgt[:, None]) + np.eye(8) * 1e-9 * (1 + np.abs(J).max())
        delta = np.linalg.solve(Hm, J.T @ (wgt * off))
        A = A + np.array([[delta[0], delta[1]], [delta[3], delta[4]]])
        c = c + np.array([delta[2], delta[5]])
        pv = pv + delta[6:8]
        if np.abs(delta[[2, 5]]).sum() < 1e-4:
            break
    J_lin = A - np.outer(c, pv)
    theta = math.atan2(-J_lin[1, 0], J_lin[0, 0])
    scale = math.sqrt(abs(np.linalg.det(J_lin)))
    return float(c[0]), float(c[1]), theta, scale


# ----------------------------------------------------------------------------- find


class _Clock:
    def __init__(self, timeout_s: float | None) -> None:
        self.c0 = time.process_time()
        self.t0 = time.perf_counter()
        self.deadline = None if timeout_s is None else self.t0 + timeout_s

    def expired(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def cpu(self) -> float:
        return time.process_time() - self.c0


def _nms_pose(poses: list[_Pose], dist: float, dtheta: float) -> list[_Pose]:
    """Drop poses within ``dist`` and ``dtheta`` of a better one (poses sorted best first)."""
    if len(poses) < 2:
        return poses
    P = np.array([[p.x, p.y, p.theta] for p in poses])
    dd = (P[:, None, 0] - P[None, :, 0]) ** 2 + (P[:, None, 1] - P[None, :, 1]) ** 2
    da = np.abs(np.mod(P[:, None, 2] - P[None, :, 2] + math.pi, 2 * math.pi) - math.pi)
    close = (dd <= dist * dist) & (da <= dtheta)
    keep = np.ones(len(poses), bool)
    for i in range(len(poses)):
        if keep[i]:
            keep[i + 1:] &= ~close[i, i + 1:]
    return [p for p, k in zip(poses, keep, strict=True) if k]


def _overlap(roi: tuple[float, float, float, float], a: Match, b: Match) -> float:
    """Intersection of two matches' model rectangles over the smaller one (HALCON's MaxOverlap)."""
    u, v, w, h = roi
    ra = ((a.u_px, a.v_px), (w * a.scale, h * a.scale), -a.angle_deg)
    rb = ((b.u_px, b.v_px), (w * b.scale, h * b.scale), -b.angle_deg)
    kind, pts = cv2.rotatedRectangleIntersection(ra, rb)
    if kind == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
        return 0.0
    inter = float(cv2.contourArea(cv2.convexHull(pts)))
    return inter / max(min(ra[1][0] * ra[1][1], rb[1][0] * rb[1][1]), 1e-9)


def _angles(start: float, extent: float, step: float) -> F64:
    if extent >= 2 * math.pi - 1e-9:
        n = int(math.ceil(2 * math.pi / step))
        return np.asarray(start + np.arange(n) * (2 * math.pi / n), dtype=np.float64)
    n = int(math.ceil(extent / step)) + 1
    return np.linspace(start, start + extent, max(n, 1))


def find(model: ShapeModel, image: NDArray[Any], search: SearchParams | None = None) -> FindResult:
    """Every instance of ``model`` in ``image`` with score >= ``min_score``, best first."""
    sp = search or SearchParams()
    clock = _Clock(sp.timeout_s)
    img = as_gray(image)
    H0, W0 = img.shape
    L = model.top_level
    pyr = pyramid(img, L + 1)
    thr_grad = model.params.min_contrast * GRAD_PER_CONTRAST
    u, v, w, h = model.roi
    min_dist = sp.min_distance_px if sp.min_distance_px is not None else min(w, h) / 3.0
    if sp.roi is not None:
        su, sv, sw, sh = sp.roi
    else:
        su, sv, sw, sh = -0.5, -0.5, W0, H0
    a0 = math.radians(sp.angle_start_deg)
    ext = math.radians(max(min(sp.angle_extent_deg, 360.0), 0.0))
    stats: dict[str, float] = {}
    # coarse levels score lower than level 0 (blur, fewer features): their thresholds stop at the
    # default's, only the final level-0 score is held to a higher minimum
    coarse_min = min(sp.min_score, 0.5)

    # 1. exhaustive search on the top level
    top = model.levels[L]
    s = 2.0 ** L
    resp = response_maps(pyr[L], thr_grad, spread=2 * TOP_STRIDE + 1)
    _, hL, wL = resp.shape
    rx0, ry0 = max(int(math.ceil(su / s)), 0), max(int(math.ceil(sv / s)), 0)
    rx1, ry1 = min(int(math.floor((su + sw) / s)), wL - 1), min(int(math.floor((sv + sh) / s)), hL - 1)
    timed_out = False
    cands: list[_Pose] = []
    if rx1 >= rx0 and ry1 >= ry0:
        thetas = _angles(a0, ext, TOP_STEP_FACTOR * top.angle_step)
        dx, dy, b = _rotated_features(top, thetas)
        T = TOP_STRIDE
        P = int(max(np.abs(dx).max(), np.abs(dy).max())) + T + 1
        pad = np.zeros((N_BINS, hL + 2 * P + T, wL + 2 * P + T), np.uint8)
        pad[:, P:P + hL, P:P + wL] = resp
        # positions on a grid of stride T (LINE-MOD's linearised memories): one sub-sampled copy of
        # the responses per grid phase, so every feature is one contiguous slice
        phases = [[np.ascontiguousarray(pad[:, py::T, px::T]) for px in range(T)] for py in range(T)]
        nh, nw = (ry1 - ry0) // T + 1, (rx1 - rx0) // T + 1
        nf = dx.shape[1]
        na = len(thetas)
        # one score map per angle, with a zero row below each so one max filter serves all
        allacc = np.zeros((na, nh + 1, nw), np.uint8)
        ay, ax = dy + P + ry0, dx + P + rx0  # padded row/column of each feature at grid node (0, 0)
        phy, phx, by_, bx_ = (ay % T).tolist(), (ax % T).tolist(), (ay // T).tolist(), (ax // T).tolist()
        bl = b.tolist()
        done = na
        for ai in range(na):
            acc = allacc[ai, :nh]
            fy, fx, oy_, ox_, ba = phy[ai], phx[ai], by_[ai], bx_[ai], bl[ai]
            for k in range(nf):
                y, x = oy_[k], ox_[k]
                np.add(acc, phases[fy[k]][fx[k]][ba[k], y:y + nh, x:x + nw], out=acc)
            if (ai & 7) == 7 and clock.expired():
                timed_out = True
                done = ai + 1
                break
        thr_top = int(math.floor(4 * nf * coarse_min * 0.7))
        # local maxima over position and angle (circular when the range is the full turn),
        # checked only where the score passes the threshold
        sub = allacc[:done]
        dil = cv2.dilate(sub.reshape(done * (nh + 1), nw), np.ones((3, 3), np.uint8)).ravel()
        flat = sub.ravel()
        idx = np.flatnonzero(flat >= thr_top)
        idx = idx[flat[idx] >= dil[idx]]
        plane = (nh + 1) * nw
        ai_ = idx // plane
        if done > 1:
            full = ext >= 2 * math.pi - 1e-9 and done == na
            for step in (-1, 1):
                nb = ai_ + step
                wrap = (nb < 0) | (nb >= done)
                nbi = idx + step * plane
                if full:
                    nbi = np.where(wrap, idx + step * plane - np.sign(step) * done * plane, nbi)
                    ok = flat[idx] >= dil[nbi]
                else:
                    ok = wrap | (flat[idx] >= dil[np.clip(nbi, 0, len(dil) - 1)])
                idx, ai_ = idx[ok], ai_[ok]
        rem = idx - ai_ * plane
        ys, xs = rem // nw, rem % nw
        sc = flat[idx]
        order = np.argsort(-sc, kind="stable")[:MAX_TOP_CANDIDATES]
        cands = [_Pose(float(T * xs[i] + rx0), float(T * ys[i] + ry0), float(thetas[ai_[i]]),
                       sc[i] / (4.0 * nf)) for i in order]
    if _TRACE is not None:
        _TRACE.append(("top", L, [(c.x, c.y, c.theta, c.score) for c in cands]))
    stats["t_top_s"] = clock.elapsed()
    stats["cpu_top_s"] = clock.cpu()
    stats["n_top_candidates"] = float(len(cands))

    # 2. discrete tracking down to level 2 (or 1 if the pyramid is short)
    lowest_discrete = min(2, L) if L >= 2 else L
    for lv in range(L - 1, lowest_discrete - 1, -1):
        if not cands or timed_out:
            break
        lm = model.levels[lv]
        last = lv == lowest_discrete
        first = lv == L - 1
        raw = response_maps(pyr[lv], thr_grad, spread=1)
        spread = _spread(raw, 3)
        cx = np.array([int(round(c.x * 2)) for c in cands], dtype=np.int64)
        cy = np.array([int(round(c.y * 2)) for c in cands], dtype=np.int64)  # plateau centres: *2, rounded
        th = np.array([c.theta for c in cands])
        nxt: list[_Pose] = []
        for start in range(0, len(cands), 32):
            sl = slice(start, start + 32)
            # below the top level the angle and position are still coarse: +-2 steps and +-2 px
            # (+-3 with the spread) there, +-1 further down
            xs_, ys_, ts_, sc_ = _track(spread, lm, cx[sl], cy[sl], th[sl], 2 if first else 1,
                                        2 if first else 1)
            if last:
                # the spread responses leave +-1 px plateaus: settle on the unspread ones
                keep = sc_ >= coarse_min * 0.7
                xs_, ys_, ts_ = xs_[keep], ys_[keep], ts_[keep]
                xs_, ys_, ts_, sc_ = _track(raw, lm, np.rint(xs_).astype(np.int64),
                                            np.rint(ys_).astype(np.int64), ts_, 1, 1)
            nxt += [_Pose(float(a), float(b_), float(t_), float(c_))
                    for a, b_, t_, c_ in zip(xs_, ys_, ts_, sc_, strict=True)
                    if c_ >= coarse_min * (0.6 if last else 0.8)]
            if clock.expired():
                timed_out = True
                break
        nxt.sort(key=lambda p: -p.score)
        if _TRACE is not None:
            _TRACE.append(("track", lv, [(c.x, c.y, c.theta, c.score) for c in nxt]))
        cands = _nms_pose(nxt, 2.0, 2.5 * lm.angle_step)
    stats["t_track_s"] = clock.elapsed()
    stats["cpu_track_s"] = clock.cpu()

    # at most a few angle hypotheses per position go on to the (costlier) least-squares stage
    per_pos: list[list[_Pose]] = []
    r_pos = (min_dist / 2.0 ** lowest_discrete) ** 2
    for c in sorted(cands, key=lambda p: -p.score):
        for grp in per_pos:
            if (grp[0].x - c.x) ** 2 + (grp[0].y - c.y) ** 2 < r_pos:
                if len(grp) < HYPOTHESES_PER_POSITION and c.score >= 0.8 * grp[0].score:
                    grp.append(c)
                break
        else:
            per_pos.append([c])
    cands = [c for grp in per_pos for c in grp]
    stats["n_tracked"] = float(len(cands))
    # 3. least-squares refinement on the remaining levels down to 0; after the first of them,
    #    hypotheses at one position (e.g. other angles of a nearly symmetric part) compete
    found: list[Match] = []
    lsq_levels = list(range(max(lowest_discrete - 1, 0), -1, -1))
    poses: list[tuple[_Pose, int, float, float]] = [(c, lowest_discrete, c.score, float("nan"))
                                                   for c in cands]
    for step, lv2 in enumerate(lsq_levels):
        nxt2: list[tuple[_Pose, int, float, float]] = []
        for pose, lv, _, _ in poses:
            if clock.expired():
                timed_out = True
                break
            f = 2.0 ** (lv - lv2)
            pose = _Pose(pose.x * f, pose.y * f, pose.theta, pose.score, pose.scale)
            sigma = model.params.edge_sigma_px if lv2 == 0 else 0.0
            pose, score, rms = _refine_lsq(
                pyr[lv2], model.levels[lv2], pose, sigma, thr_grad,
                search_px=4.5 if step == 0 else 2.0, iterations=5 if step == 0 else 1,
                fine=pyr[0] if lv2 == 0 else None, min_contrast=model.params.min_contrast,
                subset=model.levels[lv2].features if lv2 > 0 else None,
                reject_below=0.7 * coarse_min, fit_scale=lv2 <= 1 and sp.max_scale_dev > 0,
                max_scale_dev=sp.max_scale_dev, perspective=lv2 == 0 and sp.perspective)
            if score >= (coarse_min * 0.8 if lv2 > 0 else sp.min_score):
                nxt2.append((_Pose(pose.x, pose.y, pose.theta, score, pose.scale), lv2, score, rms))
        nxt2.sort(key=lambda t: -t[2])
        if _TRACE is not None:
            _TRACE.append(("lsq", lv2, [(t[0].x, t[0].y, t[0].theta, t[2]) for t in nxt2]))
        kept: list[tuple[_Pose, int, float, float]] = []
        r2 = (min_dist / 2.0 ** lv2) ** 2
        for t in nxt2:
            if all((t[0].x - o[0].x) ** 2 + (t[0].y - o[0].y) ** 2 >= r2 for o in kept):
                kept.append(t)
        poses = kept
        if timed_out:
            break
    for pose, lv, score, rms in poses:
        if lv != 0:
            continue
        if su <= pose.x <= su + sw and sv <= pose.y <= sv + sh:
            found.append(Match(pose.x, pose.y, wrap_deg(math.degrees(pose.theta)), score, rms, pose.scale))
    # final non-maximum suppression on level 0
    found.sort(key=lambda m: -m.score)
    final: list[Match] = []
    for mt in found:
        if all((mt.u_px - o.u_px) ** 2 + (mt.v_px - o.v_px) ** 2 >= min_dist ** 2
               and _overlap(model.roi, mt, o) <= sp.max_overlap for o in final):
            final.append(mt)
    if sp.max_count > 0:
        final = final[:sp.max_count]
    stats["t_total_s"] = clock.elapsed()
    stats["cpu_total_s"] = clock.cpu()
    return FindResult(final, timed_out, clock.elapsed(), stats)
