"""Shape models: edge points with gradient directions on every pyramid level, taught from an ROI.

The model is a set of edge points with their gradient directions, taken from the teach image's
ROI on every level of an image pyramid (``cv2.pyrDown``: level-``l`` pixel ``x`` lies at
level-0 ``2**l * x``); the ROI centre is the reference point. Level-0 points are moved to the
centroid edge position of their intensity profile (phase-exact for a step edge), every level
keeps a spread-out subset, and the coarse levels name the features of the discrete search.

Which edges make the model (HALCON's ``auto`` contrast and minimum component size, in our
words): an edge must reach ``AUTO_CONTRAST_FRACTION`` of the ROI's strong edges somewhere along
its run (hysteresis down to half of it), the run must be at least ``min_component_px`` long, and
edges within ``ROI_BORDER_PX`` of the ROI border or ``IMAGE_BORDER_PX`` of the image border are
left out (the border cuts them, or the pyramid made them of reflected pixels). A run is a coherent
chain (``coherent_chains``): neighbouring gradient maxima joined only along the edge and where the
direction turns little, so texture does not merge into long networks. When there are more edge
points than the model uses, the spacing between the points it keeps grows over every kept edge
alike (a short feature, such as a small hole, keeps its share: filling the budget with the best
chains first lost a bracket's small hole, bench/results/pick_real.md, 2026-12-04/05); of two points
closer than the spacing, the one of the longer, stronger chain stays (``_priority``). Normals
keep their sign (dark to bright), so the search can hold edges to their polarity. Own code:
OpenCV's Canny links texture the same way and selects nothing by length.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from vision.errors import TeachError
from vision.image import F64, U8, bilinear, gauss_peak, gradients, profile_ok, pyramid
from vision.shape.colour import COLOUR_MODES, ColourMix, channel, taught_mix
from vision.shape.patch import TeachPatch, make_patch, patch_from_dict, patch_to_dict

MIN_TOP_RADIUS_PX = 8.0
"""Automatic pyramid depth: the top level must show the model at least this large."""
MAX_TOP_FEATURES = 24  # 4 * 63 < 256: uint8 accumulators cannot overflow (keep <= 63)
MAX_TRACK_FEATURES = 64
MAX_FINE_POINTS = 240
GRAD_PER_CONTRAST = 0.25  # peak gradient (grey/px) of a blurred step of unit contrast, roughly
AUTO_CONTRAST_FRACTION = 0.3
"""Automatic contrast: a model edge must be at least this fraction of the ROI's strong edges."""
IMAGE_BORDER_PX = 2.0
"""Edges this close to the image border (level pixels) are dropped: the pyramid and the gradients
there are made of reflected pixels."""
CHAIN_MAX_TURN_DEG = 40.0
"""Two neighbouring edge pixels belong to one chain when their normals differ by less than this
(a contour rounded by the smoothing turns by well under it per pixel; texture does not)."""
ROI_BORDER_PX = 2.0
"""Edges this close to the ROI's border (level-0 pixels) are dropped: the border cuts them, and a
part of another object reaching into the ROI shows there."""


@dataclass(frozen=True)
class TeachParams:
    """How the model was taught (stored in the model file)."""

    min_contrast: float = 12.0
    """Minimum grey-value step of an edge (teach and find)."""
    num_levels: int = 0
    """Pyramid levels (0 = automatic from the ROI size)."""
    edge_sigma_px: float = 1.0
    """Gaussian smoothing before the level-0 gradients."""
    auto_contrast: bool = True
    """Choose the model's edges by contrast relative to the ROI's strongest edges (HALCON's ``auto``):
    edges weaker than ``AUTO_CONTRAST_FRACTION`` of the ROI's 90th-percentile edge are texture, not
    the part's outline. ``min_contrast`` stays the floor, and the contrast asked of image edges at find."""
    min_component_px: int = 0
    """Least length (level-0 pixels) of a connected model edge; shorter ones (texture, specks) are
    dropped. 0: automatic (a tenth of the ROI's smaller side, at least 6 px)."""
    colour: str = "auto"
    """Which channel of a colour teach image the model is made of (``vision.shape.colour``): ``"auto"``
    (the default: the chroma where its edges are strong enough, else grey), ``"grey"`` (the grey value, as
    before session 16's default) or ``"chroma"`` (the colour edges, the background's shading left out). A
    grey image is always its grey value. (A model file without ``colour`` was taught grey.)"""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_contrast) and 1.0 <= self.min_contrast <= 255.0):
            raise TeachError(f"min_contrast {self.min_contrast!r} must be 1..255 grey levels")
        if not 0 <= self.num_levels <= 8:
            raise TeachError(f"num_levels {self.num_levels} must be 0 (automatic) .. 8")
        if not (math.isfinite(self.edge_sigma_px) and 0.0 <= self.edge_sigma_px <= 5.0):
            raise TeachError(f"edge_sigma_px {self.edge_sigma_px!r} must be 0..5 px")
        if self.min_component_px < 0:
            raise TeachError(f"min_component_px {self.min_component_px} must be >= 0 (0: automatic)")
        if self.colour not in COLOUR_MODES:
            raise TeachError(f"colour {self.colour!r} must be one of {', '.join(COLOUR_MODES)}")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"min_contrast": self.min_contrast, "num_levels": self.num_levels,
                               "edge_sigma_px": self.edge_sigma_px, "auto_contrast": self.auto_contrast,
                               "min_component_px": self.min_component_px}
        if self.colour != "grey":  # (a grey model's file as before)
            out["colour"] = self.colour
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TeachParams:
        # files taught before auto contrast keep their edges as they were chosen then
        return cls(float(d.get("min_contrast", 12.0)), int(d.get("num_levels", 0)),
                   float(d.get("edge_sigma_px", 1.0)), bool(d.get("auto_contrast", False)),
                   int(d.get("min_component_px", 0)), str(d.get("colour", "grey")))


@dataclass
class LevelModel:
    """Edge points of one pyramid level, relative to the reference point (level pixels)."""

    level: int
    points: F64
    """(N, 2) sub-pixel edge points."""
    normals: F64
    """(N, 2) unit gradient directions, dark to bright (the sign is the edge's polarity)."""
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

    def mirrored(self) -> LevelModel:
        """The mirror image about the reference point's vertical axis (x -> -x)."""
        flip = np.array([-1.0, 1.0])
        return LevelModel(self.level, self.points * flip, self.normals * flip, self.features.copy())

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LevelModel:
        arr = np.asarray(d["points"], dtype=np.float64).reshape(-1, 3)
        a = np.radians(arr[:, 2])
        feats = np.asarray(d["features"], dtype=np.int64)
        if len(arr) < 3 or len(feats) == 0 or feats.max() >= len(arr) or feats.min() < 0:
            raise TeachError(f"model level {d.get('level')} is corrupt (too few points or bad indices)")
        return cls(int(d["level"]), arr[:, :2].copy(), np.stack([np.cos(a), np.sin(a)], axis=1), feats)


@dataclass
class ShapeModel:
    """A taught shape model: one ``LevelModel`` per pyramid level (index = level)."""

    levels: list[LevelModel]
    params: TeachParams
    roi: tuple[float, float, float, float]
    image_size: tuple[int, int]
    patch: TeachPatch | None = None
    """The part's pixels in the teach image (``vision.shape.patch``): the final pose is finished on
    them; ``None`` (a model read from a file without them): the edge fit alone."""
    view_tau: tuple[float, float] = (0.0, 0.0)
    """(px, rad) the error a fit of the part has beyond its own covariance by how its look changes from
    view to view (a model taught from several views, ``multi.teach_many``: the spread of the edge fit
    against the patch fit over them, ``uncertainty.view_tau``); added to every match's 1-sigma. 0: one view."""
    origin: tuple[float, float] = (0.0, 0.0)
    """The point a match reports, relative to the ROI centre the search works from (level-0 pixels of
    the teach image, unturned; ``vision.shape.frame.recentred``): a measured centre of the part. The
    search does not depend on it (HALCON's ``set_shape_model_origin``)."""
    colour: ColourMix | None = None
    """The channel of a colour image the model was taught on and is searched in (``vision.shape.colour``);
    ``None``: the grey value."""

    @property
    def top_level(self) -> int:
        return len(self.levels) - 1

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"levels": [lv.to_dict() for lv in self.levels]}
        if self.patch is not None:
            out["patch"] = patch_to_dict(self.patch)
        if self.view_tau[0] > 0 or self.view_tau[1] > 0:
            out["view_sigma"] = {"px": round(self.view_tau[0], 4), "deg": round(math.degrees(self.view_tau[1]), 4)}
        if self.origin != (0.0, 0.0):
            out["origin_px"] = [round(self.origin[0], 4), round(self.origin[1], 4)]
        if self.colour is not None:
            out["colour"] = self.colour.to_dict()
        return out

    def view_cov(self) -> F64 | None:
        """``view_tau`` as a covariance of (x, y, theta) (px, rad), or ``None`` for a one-view model."""
        if self.view_tau[0] <= 0 and self.view_tau[1] <= 0:
            return None
        return np.diag([self.view_tau[0] ** 2, self.view_tau[0] ** 2, self.view_tau[1] ** 2])

    def contour(self, u_px: float, v_px: float, angle_deg: float, scale: float = 1.0,
                mirrored: bool = False) -> tuple[F64, F64]:
        """The level-0 model edge points and their unit tangents at a pose (a match's reported point), in
        image pixels."""
        lv = self.levels[0].mirrored() if mirrored else self.levels[0]
        a = math.radians(angle_deg)
        R = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])  # CCW on screen
        o = np.array([-self.origin[0] if mirrored else self.origin[0], self.origin[1]])
        pts = scale * (lv.points - o) @ R.T + np.array([u_px, v_px])
        n = lv.normals @ R.T
        return pts, np.stack([-n[:, 1], n[:, 0]], axis=1)

    def mirrored(self) -> ShapeModel:
        """The model of the part's mirror image (a flat part lying face down)."""
        return ShapeModel([lv.mirrored() for lv in self.levels], self.params, self.roi, self.image_size,
                          None if self.patch is None else self.patch.mirrored(), self.view_tau,
                          (-self.origin[0], self.origin[1]), self.colour)

    @classmethod
    def from_dict(cls, d: dict[str, Any], params: TeachParams, roi: tuple[float, float, float, float],
                  image_size: tuple[int, int]) -> ShapeModel:
        levels = [LevelModel.from_dict(x) for x in d["levels"]]
        patch = patch_from_dict(d["patch"], levels[0].points) if d.get("patch") is not None else None
        vs = d.get("view_sigma") or {}
        tau = (float(vs.get("px", 0.0)), math.radians(float(vs.get("deg", 0.0))))
        o = d.get("origin_px") or (0.0, 0.0)
        mix = ColourMix.from_dict(d["colour"]) if d.get("colour") is not None else None
        return cls(levels, params, roi, image_size, patch, tau, (float(o[0]), float(o[1])), mix)



def _edge_points(img: U8, sigma: float, thr: float, box: tuple[float, float, float, float]
                 ) -> tuple[F64, F64, F64, NDArray[np.int64]]:
    """Sub-pixel edge points (x, y), unit normals, magnitudes and the integer pixel of each
    (where the gradient peaks: 8-connected along an edge) inside ``box`` (x0, y0, x1, y1)."""
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
    off = gauss_peak(gm, g0, gp)
    px = xs + off * nx + cx0
    py = ys + off * ny + cy0
    inside = is_max & (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)
    ipx = np.stack([xs[inside] + cx0, ys[inside] + cy0], axis=1).astype(np.int64)
    return (np.stack([px[inside], py[inside]], axis=1), np.stack([nx[inside], ny[inside]], axis=1),
            g0[inside], ipx)


def _select_edges(pts: F64, nrm: F64, mag: F64, ipx: NDArray[np.int64], box: tuple[float, float, float, float],
                  thr: float, min_len: float, border: float, size: tuple[int, int]
                  ) -> tuple[F64, F64, F64, NDArray[np.int64]]:
    """Keep the part's edges: ``border`` px inside the ROI, ``IMAGE_BORDER_PX`` inside the image
    (``size`` = (W, H) of this level), in connected runs of at least ``min_len`` pixels that reach
    ``thr`` somewhere (hysteresis from ``thr / 2``; texture and specks drop out)."""
    b, e = border, IMAGE_BORDER_PX
    x0, y0 = max(box[0] + b, e), max(box[1] + b, e)
    x1, y1 = min(box[2] - b, size[0] - 1 - e), min(box[3] - b, size[1] - 1 - e)
    inside = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    pts, nrm, mag, ipx = pts[inside], nrm[inside], mag[inside], ipx[inside]
    if len(pts) == 0:
        return pts, nrm, mag, np.zeros(0, np.int64)
    n, lab = coherent_chains(ipx, nrm)
    strong = np.zeros(n, bool)
    np.logical_or.at(strong, lab, mag >= thr)
    length = np.bincount(lab, minlength=n)[lab]
    keep = strong[lab] & (length >= min_len)
    return pts[keep], nrm[keep], mag[keep], length[keep]


def coherent_chains(ipx: NDArray[np.int64], nrm: F64) -> tuple[int, NDArray[np.int64]]:
    """Label the edge points' pixels (``ipx``, one per point) by coherent chain: two 8-neighbours
    link when their normals differ by less than ``CHAIN_MAX_TURN_DEG`` and the step between them
    runs along the edge rather than across it. The gradient maxima of a textured surface touch each
    other everywhere (a plain 8-connected labelling merges them into one network as long as the
    part's outline); linked this way they fall apart into short pieces, while a part's outline,
    however faint, stays one long chain."""
    npts = len(ipx)
    if npts == 0:
        return 0, np.zeros(0, np.int64)
    ix = ipx[:, 0] - int(ipx[:, 0].min()) + 1
    iy = ipx[:, 1] - int(ipx[:, 1].min()) + 1
    W = int(ix.max()) + 2
    index = np.full((int(iy.max()) + 2) * W, -1, np.int64)
    index[iy * W + ix] = np.arange(npts)
    cos_turn = math.cos(math.radians(CHAIN_MAX_TURN_DEG))
    rows: list[NDArray[np.int64]] = []
    cols: list[NDArray[np.int64]] = []
    for ox, oy in ((1, 0), (0, 1), (1, 1), (-1, 1)):
        j = index[(iy + oy) * W + ix + ox]
        i = np.flatnonzero(j >= 0)
        j = j[i]
        same = np.einsum("ij,ij->i", nrm[i], nrm[j]) >= cos_turn
        # a step across the edge (along the normal) joins two parallel edges, not one chain
        along = np.abs(nrm[i, 0] * ox + nrm[i, 1] * oy) <= 0.8 * math.hypot(ox, oy)
        ok = same & along
        rows.append(i[ok])
        cols.append(j[ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(npts, npts))
    n, lab = connected_components(g, directed=False)
    return int(n), np.asarray(lab, dtype=np.int64)


def _centroid_refine(img: U8, pts: F64, nrm: F64, mag: F64, length: NDArray[np.int64], min_contrast: float,
                     long_len: float) -> tuple[F64, F64, F64, NDArray[np.int64]]:
    """Move level-0 edge points to the centroid edge position; drop corners and cramped edges."""
    f = img.astype(np.float32)
    off, S, clean = profile_ok(f, pts, nrm)
    good = clean & (np.abs(off) < 0.75) & (np.abs(S) >= 0.5 * min_contrast)
    # on a real part's outline the profile is rarely one clean step (texture, a bevel, a highlight
    # beside it): points of long chains stay, at their gradient peak
    keep = good | (length >= long_len)
    pts = pts + np.where(good, off, 0.0)[:, None] * nrm
    return pts[keep], nrm[keep], mag[keep], length[keep]


def _priority(mag: F64, length: NDArray[np.int64], full_len: float) -> F64:
    """Which of two edge points closer than the model's spacing stays (``_spread_subset``): the one
    on a long coherent chain of good contrast (a part's outline) before one on a short chain
    (texture, scratches, highlights): the contrast relative to the ROI's strong edges times the
    chain's length relative to ``full_len``, each capped at 1."""
    ref = max(float(np.percentile(mag, 90)), 1e-9) if len(mag) else 1.0
    return np.minimum(mag / ref, 1.0) * np.minimum(length / max(full_len, 1.0), 1.0)


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


KeepRule = Callable[[int, F64, F64], NDArray[np.bool_]]
"""Which candidate edge points of a level may enter the model: ``(level, points, normals)`` (level
pixels relative to the reference point, unit normals) -> mask. ``vision.shape.multi`` keeps those
that the other teach images show too."""


def teach(image: NDArray[Any], roi: tuple[float, float, float, float],
          params: TeachParams | None = None, keep: KeepRule | None = None) -> ShapeModel:
    """Teach a shape model from the ROI ``(U, V, W, H)``; its centre is the reference point.

    ``keep`` (optional) filters each level's candidate edges before the point budget is filled."""
    p = params or TeachParams()
    mix = taught_mix([image], [roi], p.colour, p.edge_sigma_px, p.min_contrast * GRAD_PER_CONTRAST)
    img = channel(image, mix)
    u, v, w, h = roi
    ref = np.array([u + w / 2.0, v + h / 2.0])
    n_levels = p.num_levels if p.num_levels > 0 else auto_levels(w, h)
    pyr = pyramid(img, n_levels)
    levels: list[LevelModel] = []
    min_len = p.min_component_px if p.min_component_px > 0 else max(6, int(round(0.1 * min(w, h))))
    thr = p.min_contrast * GRAD_PER_CONTRAST
    if p.auto_contrast:
        _, _, mag0, _ = _edge_points(img, p.edge_sigma_px, thr, (u, v, u + w, v + h))
        if len(mag0):
            thr = max(thr, AUTO_CONTRAST_FRACTION * float(np.percentile(mag0, 90)))
    for lv, im in enumerate(pyr):
        s = 2.0 ** lv
        sigma = p.edge_sigma_px if lv == 0 else 0.0
        box = (u / s, v / s, (u + w) / s, (v + h) / s)
        pts, nrm, mag, ipx = _edge_points(im, sigma, 0.5 * thr, box)
        pts, nrm, mag, length = _select_edges(pts, nrm, mag, ipx, box, thr, max(3.0, min_len / s),
                                              ROI_BORDER_PX / s, (im.shape[1], im.shape[0]))
        if len(pts) < 8:
            if lv == 0:
                raise TeachError(
                    f"no edges of contrast >= {p.min_contrast:g} in the ROI: choose a region that "
                    "shows the part, or lower the minimum contrast")
            break
        if lv == 0:
            pts, nrm, mag, length = _centroid_refine(img, pts, nrm, mag, length, p.min_contrast,
                                                        0.5 * min(w, h))
            if len(pts) < 8:
                raise TeachError("too few clean edges in the ROI: choose a region that shows the part")
        pts = pts - ref / s
        if keep is not None:
            ok = keep(lv, pts, nrm)
            pts, nrm, mag, length = pts[ok], nrm[ok], mag[ok], length[ok]
            if len(pts) < 8:
                if lv == 0:
                    raise TeachError("too few of the ROI's edges are seen alike in every teach image")
                break
        prio = _priority(mag, length, 0.5 * min(w, h) / s)
        if lv == 0:
            sel = _spread_subset(pts, prio, MAX_FINE_POINTS, 2.0)
            pts, nrm, prio = pts[sel], nrm[sel], prio[sel]
            feats = np.arange(len(pts), dtype=np.int64)
        else:
            sel = _spread_subset(pts, prio, 4 * MAX_TRACK_FEATURES, 1.0)
            pts, nrm, prio = pts[sel], nrm[sel], prio[sel]
            feats = _spread_subset(pts, prio, MAX_TRACK_FEATURES, 1.5)
        levels.append(LevelModel(lv, pts, nrm, feats))
    # the top level is searched exhaustively: fewer, well spread features; drop levels that are too thin
    while len(levels) > 1 and (len(levels[-1].points) < 16 or levels[-1].radius < MIN_TOP_RADIUS_PX):
        levels.pop()
    top = levels[-1]
    # (on level 0 too: the first points in storage order would all lie along the part's top edge)
    top.features = _spread_subset(top.points, np.ones(len(top.points)), MAX_TOP_FEATURES, 1.5)
    return ShapeModel(levels, p, (u, v, w, h), (img.shape[1], img.shape[0]),
                      make_patch(img, (u, v, w, h), levels[0].points), colour=mix)

