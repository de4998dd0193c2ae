"""Teaching a shape model (``model.ShapeModel``) from an ROI of a teach image.

The model's edge points are taken from the teach image's ROI on every level of an image pyramid;
the ROI centre is the reference point. Level-0 points are moved to the centroid edge position of
their intensity profile (phase-exact for a step edge), every level keeps a spread-out subset, and
the coarse levels name the features of the discrete search. Units: pixels of each level (points
relative to the reference point once chosen), normals unit vectors (dark to bright).

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
closer than the spacing, the one of the longer, stronger chain stays (``_priority``). Own code:
OpenCV's Canny links texture the same way and selects nothing by length.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from vision.errors import TeachError
from vision.image import F64, U8, bilinear, gauss_peak, gradients, magnitude, profile_ok, pyramid
from vision.shape.colour import channel, taught_mix
from vision.shape.model import CHAIN_MAX_TURN_DEG, GRAD_PER_CONTRAST, LevelModel, ShapeModel, TeachParams
from vision.shape.patch import make_patch

MIN_TOP_RADIUS_PX = 8.0
"""Automatic pyramid depth: the top level must show the model at least this large."""
MAX_TOP_FEATURES = 24  # 4 * 63 < 256: uint8 accumulators cannot overflow (keep <= 63)
MAX_TRACK_FEATURES = 64
MAX_FINE_POINTS = 240
AUTO_CONTRAST_FRACTION = 0.3
"""Automatic contrast: a model edge must be at least this fraction of the ROI's strong edges."""
IMAGE_BORDER_PX = 2.0
"""Edges this close to the image border (level pixels) are dropped: the pyramid and the gradients
there are made of reflected pixels."""
ROI_BORDER_PX = 2.0
"""Edges this close to the ROI's border (level-0 pixels) are dropped: the border cuts them, and a
part of another object reaching into the ROI shows there."""


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
    mag = magnitude(gx, gy)
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

