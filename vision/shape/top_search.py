"""The search's first stage: the top pyramid level searched exhaustively over angles (and scales), its
candidate poses (``search.find``'s step 1).

A rotated template's score map is the sum of its features' response maps shifted by the rotated
feature offsets (line2Dup / LINE-MOD's linearised memories, ``search_kernels.accumulate_top``): one
``uint8`` add per feature and angle, all positions at once. Angle step ``TOP_STEP_FACTOR / r`` (r: the
model's radius at that level). Local maxima over position *and* angle (``search_kernels.top_maxima``),
so several angle hypotheses of a nearly symmetric part survive; the best ``TOP_BEST`` go on, and the best
of every other position scoring near the best part (``search_kernels.spread_budget``): many identical
parts all survive. Units: top-level pixels, radians, scores 0..1 (the response's fraction of its most).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.image import F64, U8
from vision.shape import search_kernels as sk
from vision.shape.model import ShapeModel
from vision.shape.refine import Pose
from vision.shape.responses import N_BINS, response_maps, rotated_features
from vision.shape.tracking import Clock
from vision.types import SearchParams

TOP_STEP_FACTOR = 1.8
"""Top-level angle step in units of 1/r: the outermost feature moves <= 0.7 px off a step."""
TOP_BEST = 64
"""The best top-level candidates taken wherever they lie (a part's cluster of maxima at
neighbouring positions and angles: a partly hidden part is often found through one of its
cluster's lesser members)."""
TOP_PER_POSITION = 1
TOP_EXTRA_OF_BEST = 0.7
"""Beyond ``TOP_BEST``, ``TOP_PER_POSITION`` more from each neighbourhood (half the model's
top-level radius) not yet represented, scoring at least this fraction of the best candidate and the
coarse minimum: the strongest parts' clusters alone would fill the list, and a full tray of 30
identical parts was 12-16 found."""
MAX_TOP_CANDIDATES = 160
"""Most top-level candidates (bounds what a textured image, a maximum everywhere, can cost)."""

Box = tuple[float, float, float, float]
"""A search region (U, V, W, H), level-0 pixels."""


def _angles(start: float, extent: float, step: float) -> F64:
    if extent >= 2 * math.pi - 1e-9:
        n = int(math.ceil(2 * math.pi / step))
        return np.asarray(start + np.arange(n) * (2 * math.pi / n), dtype=np.float64)
    n = int(math.ceil(extent / step)) + 1
    return np.linspace(start, start + extent, max(n, 1))


def search_scales(sp: SearchParams, radius: float) -> list[float]:
    """Scales searched on the top level: steps that move the outermost feature about one pixel."""
    if sp.scale_max - sp.scale_min < 1e-9:
        return [1.0]
    n = max(int(math.ceil((sp.scale_max - sp.scale_min) * radius)), 1)
    return [float(x) for x in np.linspace(sp.scale_min, sp.scale_max, n + 1)]


def top_search(model: ShapeModel, level_img: U8, thr_grad: float, search_box: Box, a0: float,
                ext: float, thr_frac: float, extra_min: float, scales: list[float],
                clock: Clock) -> tuple[list[Pose], bool]:
    """Exhaustive search of the top level over angles and ``scales``: candidate poses (top-level
    pixels), best first, and whether time ran out."""
    resp = response_maps(level_img, thr_grad, spread=3)
    out: list[Pose] = []
    timed_out = False
    for scale in scales:
        cands, timed_out = _top_one_scale(model, resp, search_box, a0, ext, thr_frac, extra_min, scale, clock)
        out += cands
        if timed_out:
            break
    out.sort(key=lambda c: -c.score)
    if len(scales) > 1:
        out = _within_budget(out, model.levels[model.top_level].radius, extra_min)
    return out, timed_out


def _within_budget(cands: list[Pose], radius: float, extra_min: float) -> list[Pose]:
    """``cands`` (sorted best first, top-level pixels) under the candidate budget (``_budget``)."""
    keep = _budget(np.array([c.x for c in cands]), np.array([c.y for c in cands]),
                   np.array([c.score for c in cands]), radius, extra_min)
    return [cands[i] for i in keep.tolist()]


def _budget(xs: F64, ys: F64, sc: F64, radius: float, extra_min: float) -> NDArray[np.int64]:
    """Indices kept of candidates sorted best first (float64 arrays, top-level pixels; ``radius``: the
    model's top-level radius): ``TOP_BEST``, then ``TOP_EXTRA_OF_BEST`` and ``TOP_PER_POSITION``."""
    if len(sc) == 0:
        return np.zeros(0, np.int64)
    bar = max(extra_min, TOP_EXTRA_OF_BEST * float(sc[0]))
    return sk.spread_budget(xs, ys, sc, radius / 2.0, TOP_BEST, TOP_PER_POSITION, bar, MAX_TOP_CANDIDATES)


def _top_one_scale(model: ShapeModel, resp: U8, search_box: Box, a0: float, ext: float, thr_frac: float,
                   extra_min: float, scale: float, clock: Clock) -> tuple[list[Pose], bool]:
    L = model.top_level
    top = model.levels[L]
    s = 2.0 ** L
    su, sv, sw, sh = search_box
    _, hL, wL = resp.shape
    rx0, ry0 = max(int(math.ceil(su / s)), 0), max(int(math.ceil(sv / s)), 0)
    rx1, ry1 = min(int(math.floor((su + sw) / s)), wL - 1), min(int(math.floor((sv + sh) / s)), hL - 1)
    if rx1 < rx0 or ry1 < ry0:
        return [], False
    timed_out = False
    thetas = _angles(a0, ext, TOP_STEP_FACTOR * top.angle_step / scale)
    dx, dy, b = rotated_features(top, thetas, np.full(len(thetas), scale))
    P = int(max(np.abs(dx).max(), np.abs(dy).max())) + 2
    Hp, Wp = hL + 2 * P + 2, wL + 2 * P + 1
    pad = np.zeros((N_BINS, Hp, Wp), np.uint8)
    pad[:, P:P + hL, P:P + wL] = resp
    padf = pad.reshape(N_BINS, Hp * Wp)
    nh, nw = ry1 - ry0 + 1, rx1 - rx0 + 1
    nf = dx.shape[1]
    na = len(thetas)
    # LINE-MOD's linearised memories (search_kernels.accumulate_top): columns >= nw of a row are
    # wrapped garbage, and a zero row below each angle's plane keeps the planes apart
    lin = np.zeros((na, (nh + 1) * Wp), np.uint8)
    start = np.ascontiguousarray((dy + P + ry0) * Wp + dx + P + rx0)
    b = np.ascontiguousarray(b)
    run = nh * Wp
    done = 0
    while done < na:
        nxt = min(done + 8, na)
        sk.accumulate_top(padf, b, start, run, lin, done, nxt)
        done = nxt
        if done < na and clock.expired():
            timed_out = True
            break
    thr_top = int(math.floor(4 * nf * thr_frac))
    # local maxima over position and angle (circular when the range is the full turn)
    full = ext >= 2 * math.pi - 1e-9 and done == na
    planes = lin[:done].reshape(done, nh + 1, Wp)  # a view: its columns < nw are the score planes
    # isolated: OpenCV would read the view's columns >= nw (the wrapped garbage) as its border otherwise
    dil = cv2.dilate(planes.reshape(done * (nh + 1), Wp)[:, :nw], np.ones((3, 3), np.uint8),
                     borderType=cv2.BORDER_CONSTANT | cv2.BORDER_ISOLATED).reshape(done, nh + 1, nw)
    ai_, ys, xs, sc = sk.top_maxima(planes, dil, nh, thr_top, full)
    order = np.argsort(-sc, kind="stable")
    order = order[_budget(xs[order].astype(np.float64), ys[order].astype(np.float64), sc[order] / (4.0 * nf),
                          top.radius, extra_min)]
    cands = [Pose(float(x + rx0), float(y + ry0), float(t), float(v) / (4.0 * nf), scale)
             for x, y, t, v in zip(xs[order].tolist(), ys[order].tolist(), thetas[ai_[order]].tolist(),
                                   sc[order].tolist(), strict=True)]
    return cands, timed_out
