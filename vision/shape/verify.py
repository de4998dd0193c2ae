"""Verification of a refined match: second, independent looks at the part before it is answered.

The search's score (``score.direction_score``) is the fraction of the model's edge points seen
where they should be. A false candidate can reach it in ways a real part cannot: its seen points
bunched on one straight edge of the model, their contrast flipping from point to point (texture,
or pieces of two neighbouring parts), a feature of the part plainly absent in a clean region (a
similar part without that hole, the part's mirror image), edges no stronger than the image's noise,
or edges that a better match already explains (a ghost straddling two touching identical parts).
Each check reads the per-point detail of the final pose (``score.PointDetail``) and the model's
own features (its edge chains, ``features``); each threshold is a property of the model or the
image, not a number fitted to a data set:

- ``coverage``: the share of the model's contour (by points) in features at least half seen. A
  match needs ``min_score`` of it, as of its score: the score's fraction must be spread over
  the part, not bunched on one edge.
- ``polarity``: of neighbouring seen points along a feature, the share whose contrast has the same
  sign. A part's contrast changes sign only where its background does (a few places); texture's
  flips at random (0.5). A match needs more than chance by three standard deviations of a coin's
  share over its pairs (``0.5 + 1.5 / sqrt(pairs)``), and never more than ``POLARITY_MIN``.
- ``contrast``: the median gradient of the seen edges over what the image's noise reaches around
  the part (``score.grad_noise``, 4 deviations). A match needs at least 1.
- ``missing``: a feature of at least ``MISSING_MIN_FRACTION`` of the model's points, less than a
  quarter seen, inside the region the seen points span, where the image shows no edge above its
  noise: nothing hides it there, so the part lacks it (an occluder, a shadow or a neighbour would
  show an edge of its own). Any such feature rejects the match. Points inside a better match's
  hull (``hidden_by``: a part lying on this one) are hidden: neither missing, nor absent for
  ``surround``.
- ``surround``: how far the model's centre (the centroid of its points) lies inside the convex hull
  of the evidenced points (seen with a seen neighbour along their chain, or outside the image: the
  border hides them), over how far it lies inside the hull of the whole model. A part is evidenced around
  its centre: 1 when seen all round, about 0 for its half (every seen edge on one side of a line
  through the centre), negative for less. A match whose contour lies in features at least half
  seen but for less than ``MISSING_MIN_FRACTION`` (its coverage) lacks no piece and is not judged by
  it (a small part's sparse fit sits on one side within its chains). Otherwise a match needs
  ``SearchParams.min_surround`` (0.2): on a
  round part a straight cut that leaves less hides more than 37 % of its area, so a half (50 %) is
  not answered as the part, a part 30 % hidden is (0.28 and more on the bench's occlusions). A
  half is a part half hidden by an occluder the colour of the background: the image is the same,
  so it is the share hidden that decides, and ``min_surround 0`` answers such fragments.
- ``unclaimed`` (in ``search.find``'s suppression): the score counting only the seen points that no
  better match's contour covers; below ``min_score`` the match is a ghost of better ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from vision.image import F64
from vision.shape.model import CHAIN_MAX_TURN_DEG, LevelModel
from vision.shape.score import SCORE_MAX_ANGLE_DEG, PointDetail
from vision.shape.search_kernels import run_sizes
from vision.shape.small_kernels import median

POLARITY_MIN = 0.75
"""The most a match's polarity coherence is asked: halfway between a part's (1 but for a few
background changes) and texture's (0.5); with many pairs the test against chance asks less (a
specular part on wood flips more than a machined one on a table)."""
MISSING_MIN_FRACTION = 0.05
"""A feature smaller than this share of the model's points is not judged missing (a glint, a speck
of texture in the teach image)."""
MISSING_SEEN_MAX = 0.25
FLAT_SHARE = 0.8
"""A feature is absent when at least this share of its unseen points has no edge above the noise."""
SURROUND_MIN = 0.2
"""Default ``SearchParams.min_surround``: see ``surround`` above."""
LINK_SPACINGS = 2.5
"""Model points closer than this many typical spacings (median nearest neighbour) are neighbours on
a chain: the model keeps a spread-out subset, whose gaps along an edge reach twice the spacing."""
CLAIM_PX = 1.5
"""A seen point within this distance of a better match's model point (direction within the score's
angle limit) is that match's edge."""


@dataclass
class Features:
    """The model's level-0 edge chains: a label per point and the linked neighbour pairs."""

    labels: NDArray[np.int64]
    count: int
    pairs: NDArray[np.int64]
    """(K, 2) indices of neighbouring points along a chain."""


def features(lm: LevelModel) -> Features:
    """The chains of the level-0 model (cached on ``lm``): points linked when closer than ``LINK_SPACINGS`` times the
    model's typical spacing and turned by less than ``CHAIN_MAX_TURN_DEG``."""
    cached = lm.__dict__.get("_features")
    if isinstance(cached, Features):
        return cached
    pts, nrm = lm.points, lm.normals
    n = len(pts)
    d = np.hypot(pts[:, None, 0] - pts[None, :, 0], pts[:, None, 1] - pts[None, :, 1])
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1))) if n > 1 else 1.0
    cosang = np.abs(nrm @ nrm.T)
    link = (d <= LINK_SPACINGS * spacing) & (cosang >= math.cos(math.radians(CHAIN_MAX_TURN_DEG)))
    i, j = np.nonzero(np.triu(link))
    g = coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(n, n))
    count, lab = connected_components(g, directed=False)
    out = Features(np.asarray(lab, np.int64), int(count), np.stack([i, j], axis=1).astype(np.int64))
    lm.__dict__["_features"] = out
    return out


@dataclass
class Verdict:
    scores: dict[str, float]
    rejected_because: str | None


def verify(lm: LevelModel, q: F64, detail: PointDetail, grad_noise: float, min_score: float,
           score: float, min_surround: float = SURROUND_MIN, hidden: NDArray[np.bool_] | None = None) -> Verdict:
    """The checks of a match whose level-0 model points lie at ``q`` (image pixels); ``hidden``: its
    points that lie on a better match (``hidden_by``): something hides them, so they are neither
    missing nor absent from around the centre."""
    hid = hidden if hidden is not None else np.zeros(len(q), bool)
    f = features(lm)
    seen = (detail.agree > 0) & detail.visible
    vis = detail.visible
    n_pts = len(q)
    scores: dict[str, float] = {"edge": round(score, 4)}
    # coverage: the contour's share in features at least half seen (of the visible ones)
    n_vis_f = np.bincount(f.labels[vis], minlength=f.count)
    n_seen_f = np.bincount(f.labels[seen], minlength=f.count)
    half_seen = (n_vis_f > 0) & (2 * n_seen_f >= n_vis_f)
    coverage = float(n_vis_f[half_seen].sum()) / max(float(n_vis_f.sum()), 1.0)
    scores["coverage"] = round(coverage, 4)
    # polarity coherence along the chains
    a, b = f.pairs[:, 0], f.pairs[:, 1]
    both = seen[a] & seen[b]
    n_pairs = int(np.count_nonzero(both))
    polarity = float(np.count_nonzero(detail.sign[a][both] == detail.sign[b][both])) / n_pairs if n_pairs else 1.0
    scores["polarity"] = round(polarity, 4)
    contrast = median(detail.gmax[seen]) / max(grad_noise, 1e-9) if seen.any() else 0.0
    scores["contrast"] = round(min(contrast, 999.0), 2)
    maybe = (n_vis_f >= MISSING_MIN_FRACTION * n_pts) & (n_seen_f < MISSING_SEEN_MAX * n_vis_f)
    # the region seen: the hull of the features at least half seen (a stray agreement in clutter beyond
    # an occluder's edge does not stretch it over the hidden part)
    seen_region = seen & half_seen[f.labels]
    missing = (_missing(f, q, seen, seen_region, vis, detail.gmax, grad_noise, np.flatnonzero(maybe), hid)
               if maybe.any() else [])
    scores["missing_features"] = float(len(missing))
    # evidenced: seen points with a seen neighbour along their chain (a lone agreement in clutter does
    # not stretch the hull), and the points outside the image (the border hides them)
    linked = np.zeros(n_pts, bool)
    linked[a[both]] = True
    linked[b[both]] = True
    surround = _surround(q, linked | ~vis | hid, f.pairs)
    scores["surround"] = round(surround, 4)
    if score < min_score:
        return Verdict(scores, f"score {score:.2f} < min_score {min_score:g}")
    if coverage < min_score:
        return Verdict(scores, f"its seen edges bunch on a part of the contour: coverage {coverage:.2f} "
                               f"< min_score {min_score:g}")
    pol_min = min(POLARITY_MIN, 0.5 + 1.5 / math.sqrt(max(n_pairs, 1)))
    if polarity <= pol_min:
        return Verdict(scores, f"the contrast along its edges flips at random (coherence {polarity:.2f} <= "
                               f"{pol_min:.2f} over {n_pairs} neighbours): texture or pieces of other parts, "
                               "not one part")
    if contrast < 1.0:
        return Verdict(scores, f"its edges are not above the image's noise (contrast {contrast:.2f} < 1)")
    if missing:
        x, y = missing[0]
        return Verdict(scores, f"a feature of the part is missing at ({x:.0f}, {y:.0f}): no edge there, "
                               "and nothing hides it")
    # last: the other checks passed, so the setting it names would answer the match. A match whose
    # features are all at least half seen but for specks (< MISSING_MIN_FRACTION of the contour) lacks
    # no piece: its seen points may sit on one side within each chain (a small part's sparse fit)
    if surround < min_surround and 1.0 - coverage >= MISSING_MIN_FRACTION:
        return Verdict(scores, f"its seen edges lie on one side of the part's centre (surround {surround:.2f} "
                               f"< min_surround {min_surround:g}): a piece of the part, e.g. its half, or the part "
                               f"more than about 40 % hidden; min_surround {math.floor(surround * 100) / 100:g} "
                               "would answer it")
    return Verdict(scores, None)


SURROUND_DIRECTIONS = 72
"""Directions (5 deg apart) in which ``_surround`` measures how far the evidence reaches."""
SURROUND_SPECK = 0.025
"""Evidence in runs (linked along the model's chains) of fewer than this share of the model's points
(at least 3) does not count: a clutter edge touching the model's contour for a few points."""
_TURNS = np.arange(SURROUND_DIRECTIONS) * (2 * math.pi / SURROUND_DIRECTIONS)
_DIRECTIONS = np.stack([np.cos(_TURNS), np.sin(_TURNS)])
"""(2, ``SURROUND_DIRECTIONS``) the unit directions of ``_surround`` (computed once)."""


def _surround(q: F64, evidenced: NDArray[np.bool_], pairs: NDArray[np.int64]) -> float:
    """How far the evidenced points reach around the centroid of ``q`` (all model points at the pose,
    image px), as the inset of the centre in their convex hull (the least reach over
    ``SURROUND_DIRECTIONS``) over the whole model's: 1 when seen all round (clipped), about 0 for a
    half, negative when the centre lies outside. Only runs of evidence along the chains (``pairs``)
    of at least ``SURROUND_SPECK`` of the points count."""
    n = len(q)
    size = run_sizes(n, np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]), evidenced)
    keep = size >= max(3, int(math.ceil(SURROUND_SPECK * n)))
    d = q - q.mean(axis=0)
    proj = d @ _DIRECTIONS
    full = float(proj.max(axis=0).min())
    if full <= 1e-6:
        return 1.0  # the model's points lie on a line: no inside to be surrounded
    if not keep.any():
        return -1.0
    return float(np.clip(proj[keep].max(axis=0).min() / full, -1.0, 1.0))


def _missing(f: Features, q: F64, seen: NDArray[np.bool_], region: NDArray[np.bool_], vis: NDArray[np.bool_],
             gmax: F64, grad_noise: float, ks: NDArray[np.int64],
             hidden: NDArray[np.bool_]) -> list[tuple[float, float]]:
    """Centres (image px) of the features ``ks`` (large, mostly unseen) that are absent where nothing
    could hide them: no edge above the noise, not on a better match (``hidden``), inside the hull of
    the ``region`` points."""
    if np.count_nonzero(region) < 3:
        return []
    hull = cv2.convexHull(q[region].astype(np.float32))
    out = []
    flat = (gmax < grad_noise) & ~hidden
    for k in ks.tolist():
        idx = np.flatnonzero((f.labels == k) & vis)
        unseen = idx[~seen[idx]]
        if np.count_nonzero(flat[unseen]) < FLAT_SHARE * len(unseen):
            continue
        c = q[idx].mean(axis=0)
        # inside the seen region by more than the reach of the score (a feature on the seen region's
        # rim may be where an occluder's straight cut runs)
        if cv2.pointPolygonTest(hull, (float(c[0]), float(c[1])), True) > 2.0:
            out.append((float(c[0]), float(c[1])))
    return out


Contour = tuple[float, float, float, F64, F64]
"""A kept match's contour: centre x, y and radius (px), points and normals at its pose."""


def hidden_by(q: F64, others: list[Contour]) -> NDArray[np.bool_]:
    """Which of a candidate's model points ``q`` (image px) lie inside the convex hull of a kept
    (better) match's points: a part lying on it hides them (parts in a heap)."""
    out = np.zeros(len(q), bool)
    if not others:
        return out
    c = q.mean(axis=0)
    rad = float(np.sqrt(((q - c) ** 2).sum(axis=1).max()))
    for ox, oy, orad, qo, _ in others:
        if (ox - c[0]) ** 2 + (oy - c[1]) ** 2 > (rad + orad) ** 2:
            continue
        h = cv2.convexHull(qo.astype(np.float32)).reshape(-1, 2).astype(np.float64)
        e = np.roll(h, -1, axis=0) - h  # edges of the convex polygon, in order
        cross = e[None, :, 0] * (q[:, None, 1] - h[None, :, 1]) - e[None, :, 1] * (q[:, None, 0] - h[None, :, 0])
        out |= (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    return out


def contour_of(q: F64, n: F64) -> Contour:
    c = q.mean(axis=0)
    return float(c[0]), float(c[1]), float(np.sqrt(((q - c) ** 2).sum(axis=1).max())), q, n


def claimed(q: F64, n: F64, seen: NDArray[np.bool_], others: list[Contour]) -> NDArray[np.bool_]:
    """Which seen points of a match lie on the contour of one of ``others`` (kept matches): within
    ``CLAIM_PX`` and the direction within the score's angle limit."""
    out = np.zeros(len(q), bool)
    if not others or not seen.any():
        return out
    c0 = math.cos(math.radians(SCORE_MAX_ANGLE_DEG))
    idx = np.flatnonzero(seen)
    qs = q[idx]
    lo, hi = qs.min(axis=0) - CLAIM_PX, qs.max(axis=0) + CLAIM_PX
    cx, cy, rad, _, _ = contour_of(q, n)
    for ox, oy, orad, qo, no in others:
        if (ox - cx) ** 2 + (oy - cy) ** 2 > (rad + orad + CLAIM_PX) ** 2:
            continue  # apart (most pairs on a full tray)
        # only the other's points inside this match's box (on a full tray most others are apart)
        near_box = (qo[:, 0] >= lo[0]) & (qo[:, 0] <= hi[0]) & (qo[:, 1] >= lo[1]) & (qo[:, 1] <= hi[1])
        if not near_box.any():
            continue
        qo, no = qo[near_box], no[near_box]
        d2 = (qs[:, None, 0] - qo[None, :, 0]) ** 2 + (qs[:, None, 1] - qo[None, :, 1]) ** 2
        near = d2 <= CLAIM_PX ** 2
        if not near.any():
            continue
        cos = np.abs(n[idx] @ no.T)
        out[idx[(near & (cos >= c0)).any(axis=1)]] = True
    return out
