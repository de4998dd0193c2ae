"""Shape-based search: every instance of a taught part at any rotation, coarse to fine.

1. **Top level, exhaustive** (line2Dup / LINE-MOD style): a rotated template's score map is the
   sum of its features' response maps shifted by the rotated feature offsets — one vectorised
   ``uint8`` add per feature and angle, all positions at once. Angle step ``1.8/r`` (r: model
   radius at that level). Local maxima over position *and* angle, so several angle hypotheses
   of a nearly symmetric part survive; the best 64 go on, and the best of every other position
   scoring near the best part (``search_kernels.spread_budget``): many identical parts all survive
   (``top_search``).
2. **Tracking down the pyramid** (batched gathers, ``responses.track``): on the level below the
   top, +-2 angle steps and +-2 px on spread responses, tracked again from where the best lies on
   the window's edge (``tracking.climb``: a partly hidden part's top-level peak can sit a few pixels off);
   on each finer level +-1; on the last discrete level a second pass on unspread responses settles
   the +-1 px plateaus.
3. **Least-squares refinement** (``refine.refine_lsq``) on level 1, then level 0.
4. **Verification** (``verify.verify``, in the final suppression ``_verified``): a second look at each
   refined pose (coverage of the model's features, contrast polarity along its chains, contrast over
   the image's noise, a feature missing where nothing hides it, edges already claimed by a better
   match, the seen edges around the part's centre); a candidate that fails is not answered but
   listed in ``FindResult.rejected`` with why.

The score (``score.direction_score``, HALCON's metric in our words) is the edge-direction
agreement at the final pose averaged over the model points that lie inside the image: each point
contributes the agreement of its normal with the image edge's gradient direction within 1-1.5 px
along the normal, with the polarity rule asked (``use_polarity``, ``ignore_global_polarity``,
``ignore_local_polarity``). It is the fraction of the visible model edges seen where they should
be, so it falls smoothly with occlusion, and a part running off the image is scored on what is
seen (down to ``min_visible`` of its points). With ``mirrored`` the model's mirror image is searched
too; with a scale range, the top level searches scales as well as angles. Greediness sets how far
below ``min_score`` a top-level candidate may start. Matches closer than a third of the ROI's
smaller side, or whose model rectangles overlap a better match by more than ``max_overlap``, are
dropped. Each match reports the model points that agreed (``n_points``) and were visible.

Own code over OpenCV primitives: OpenCV has no rotation-invariant shape matcher with sub-pixel
refinement (``matchTemplate`` is translation-only, ``matchShapes`` gives no pose).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.image import F64, U8, pyramid, wrap_deg
from vision.shape.colour import channel, interior_verdict
from vision.shape.frame import match_at_origin, origin_at
from vision.shape.model import GRAD_PER_CONTRAST, ShapeModel
from vision.shape.patch import TeachPatch
from vision.shape.patch import finish as finish_on_patch
from vision.shape.refine import Pose, Refined, refine_lsq
from vision.shape.top_search import Box, search_scales, top_search
from vision.shape.tracking import Clock, few_per_position, track_down
from vision.shape.uncertainty import sigma_of
from vision.shape.verify import Contour, claimed, contour_of, hidden_by, verify
from vision.shape.warmup import warm_up
from vision.types import MIN_SCORE_FLOOR, Candidate, FindResult, Match, Rejected, SearchParams

TIE_SCORE = 0.02
TIE_MIN_TURN_DEG = 10.0
"""Two refined hypotheses at one position, turned more than ``TIE_MIN_TURN_DEG`` apart and within
``TIE_SCORE`` of each other, both go on to level 0 (not two copies of one pose)."""
MIRROR_MARGIN = 0.02



def overlap(roi: Box, a: Match, b: Match) -> float:
    """Intersection of two matches' model rectangles over the smaller one (HALCON's MaxOverlap)."""
    u, v, w, h = roi
    if math.hypot(a.u_px - b.u_px, a.v_px - b.v_px) > 0.5 * math.hypot(w, h) * (a.scale + b.scale):
        return 0.0  # the rectangles' circumscribed circles are apart (most pairs on a full tray)
    ra = ((a.u_px, a.v_px), (w * a.scale, h * a.scale), -a.angle_deg)
    rb = ((b.u_px, b.v_px), (w * b.scale, h * b.scale), -b.angle_deg)
    kind, pts = cv2.rotatedRectangleIntersection(ra, rb)
    if kind == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
        return 0.0
    inter = float(cv2.contourArea(cv2.convexHull(pts)))
    return inter / max(min(ra[1][0] * ra[1][1], rb[1][0] * rb[1][1]), 1e-9)


Hypothesis = tuple[Pose, int, Refined]


def _refine_down(model: ShapeModel, pyr: list[U8], thr_grad: float, cands: list[Pose],
                 lowest_discrete: int, sp: SearchParams, coarse_min: float, min_dist: float,
                 clock: Clock) -> tuple[list[Hypothesis], Refined | None, bool]:
    """Least-squares refinement on the remaining levels down to 0: (pose, level, refined) each,
    the best level-0 result below ``min_score`` (to say why nothing was found), and time-out.

    After the first refined level, hypotheses at one position (e.g. other angles of a nearly
    symmetric part) compete.
    """
    timed_out = False
    best_low: Refined | None = None
    poses: list[Hypothesis] = [(c, lowest_discrete, Refined(c, c.score, float("nan"))) for c in cands]
    for step, lv2 in enumerate(range(max(lowest_discrete - 1, 0), -1, -1)):
        nxt2: list[Hypothesis] = []
        for pose, lv, _ in poses:
            if clock.expired():
                timed_out = True
                break
            f = 2.0 ** (lv - lv2)
            pose = Pose(pose.x * f, pose.y * f, pose.theta, pose.score, pose.scale)
            sigma = model.params.edge_sigma_px if lv2 == 0 else 0.0
            r = refine_lsq(
                pyr[lv2], model.levels[lv2], pose, sigma, thr_grad,
                search_px=4.5 if step == 0 else 2.0, iterations=5 if step == 0 else 1,
                fine=pyr[0] if lv2 == 0 else None, min_contrast=model.params.min_contrast,
                subset=model.levels[lv2].features if lv2 > 0 else None,
                reject_below=0.7 * coarse_min, fit_scale=lv2 <= 1 and sp.max_scale_dev > 0,
                max_scale_dev=sp.max_scale_dev, perspective=lv2 == 0 and sp.perspective,
                polarity=sp.polarity, min_visible=sp.min_visible, extras_from=sp.min_score)
            if r.score >= (coarse_min * 0.8 if lv2 > 0 else sp.min_score):
                nxt2.append((r.pose, lv2, r))
            elif lv2 == 0 and (best_low is None or r.score > best_low.score):
                best_low = r
        nxt2.sort(key=lambda t: -t[2].score)
        kept: list[Hypothesis] = []
        r2 = (min_dist / 2.0 ** lv2) ** 2
        for t in nxt2:
            rivals = [o for o in kept if (t[0].x - o[0].x) ** 2 + (t[0].y - o[0].y) ** 2 < r2]
            # a near tie at one position (the other turn of a symmetric part) goes on to level 0 too:
            # a coarse level cannot tell which of the two fits the full-resolution edges better
            if not rivals or (lv2 > 0 and len(rivals) == 1 and t[2].score >= rivals[0][2].score - TIE_SCORE
                              and abs(wrap_deg(math.degrees(t[0].theta - rivals[0][0].theta))) > TIE_MIN_TURN_DEG):
                kept.append(t)
        poses = kept
        if timed_out:
            break
    return poses, best_low, timed_out


Found = tuple[Match, Refined]


def _search_one(model: ShapeModel, pyr: list[U8], sp: SearchParams, mirrored: bool, clock: Clock,
                stats: dict[str, float]) -> tuple[list[Found], Refined | None, bool]:
    """Level-0 matches of one model (the taught one or its mirror image), not yet suppressed."""
    H0, W0 = pyr[0].shape
    L = model.top_level
    thr_grad = model.params.min_contrast * GRAD_PER_CONTRAST
    u, v, w, h = model.roi
    min_dist = sp.min_distance_px if sp.min_distance_px is not None else min(w, h) / 3.0
    box: Box = sp.roi if sp.roi is not None else (-0.5, -0.5, W0, H0)
    su, sv, sw, sh = box
    a0 = math.radians(sp.angle_start_deg)
    ext = math.radians(sp.angle_extent_deg)
    # coarse levels score lower than level 0 (blur, fewer features): their thresholds stop at the
    # default's, only the final level-0 score is held to a higher minimum. Greediness sets how far
    # below it a top-level candidate may start (0.4 .. 0.73 of it; 0.7 at the default 0.9).
    coarse_min = min(sp.min_score, 0.5)
    thr_frac = coarse_min * (0.4 + sp.greediness / 3.0)
    cands, timed_out = top_search(model, pyr[L], thr_grad, box, a0, ext, thr_frac, coarse_min,
                                   search_scales(sp, model.levels[L].radius), clock)
    stats["t_top_s"] = clock.elapsed()
    stats["cpu_top_s"] = clock.cpu()
    stats["n_top_candidates"] = stats.get("n_top_candidates", 0.0) + len(cands)
    lowest_discrete = min(2, L) if L >= 2 else L
    if not timed_out:
        cands, timed_out = track_down(model, pyr, thr_grad, cands, lowest_discrete, coarse_min, clock)
    stats["t_track_s"] = clock.elapsed()
    stats["cpu_track_s"] = clock.cpu()
    cands = few_per_position(cands, min_dist / 2.0 ** lowest_discrete)
    stats["n_tracked"] = stats.get("n_tracked", 0.0) + len(cands)
    poses, low, t_out = _refine_down(model, pyr, thr_grad, cands, lowest_discrete, sp, coarse_min, min_dist,
                                     clock)
    found = [(_match_of(p, r, mirrored), r)
             for p, lv, r in poses if lv == 0 and su <= p.x <= su + sw and sv <= p.y <= sv + sh]
    return found, low, timed_out or t_out


def _match_of(p: Pose, r: Refined, mirrored: bool) -> Match:
    """The match of a level-0 hypothesis at its edge fit's pose, its 1-sigma not yet set (``_finish``
    completes an answered one: the rest are never reported, and their 1-sigma would cost an eigen
    decomposition each)."""
    return Match(p.x, p.y, wrap_deg(math.degrees(p.theta)), r.score, r.rms_px, p.scale, mirrored,
                 r.n_points, r.n_visible, float("nan"), float("nan"))


def _finish(patch: TeachPatch | None, pyr: list[U8], mt: Match, r: Refined, T0: F64 | None = None) -> Match:
    """``mt``'s pose finished on the taught patch (``patch.finish``), with the 1-sigma of the merged fit
    and the patch's scores; without a patch or where it cannot be fitted, the edge fit's pose with its
    jackknife 1-sigma. ``T0``: the model's teach views' extra error (``ShapeModel.view_cov``), in either.
    Only answered matches are finished: the rest cost nothing more."""
    done = None if patch is None else finish_on_patch(patch, pyr, mt.u_px, mt.v_px, math.radians(mt.angle_deg),
                                                      mt.scale, r.cov, T0)
    if done is None and r.cov is not None and np.all(np.isfinite(r.cov)):
        # no patch to finish on (or its interior does not match): the edge fit's own honest 1-sigma (its
        # block jackknife: a stretch of edge pulled by shading or texture shows in it)
        mt.sigma_angle_deg, mt.sigma_px = sigma_of(r.cov if T0 is None else r.cov + T0)
    elif done is not None:
        mt.u_px, mt.v_px, th, mt.sigma_angle_deg, mt.sigma_px, extra = done
        mt.angle_deg = wrap_deg(math.degrees(th))
        mt.scores.update(extra)
    return mt


def find(model: ShapeModel, image: NDArray[Any], search: SearchParams | None = None) -> FindResult:
    """Every instance of ``model`` in ``image`` with score >= ``min_score``, best first.

    Never raises on an image: an empty, constant or too small image answers no match (with the
    reason in ``FindResult.reason()``); a part partly outside the image is scored on its visible
    model points (``SearchParams.min_visible``).
    """
    sp = search or SearchParams()
    warm_up()  # the compiled loops are loaded (or compiled) before the search's clock starts
    clock = Clock(sp.timeout_s)
    img = channel(image, model.colour)
    stats: dict[str, float] = {}
    if img.size == 0 or min(img.shape) < 8:
        return FindResult([], False, clock.elapsed(), stats, None, sp.min_score)
    pyr = pyramid(img, model.top_level + 1)
    found: list[Found] = []
    low: tuple[Refined, bool] | None = None
    timed_out = False
    for mirrored in (False, True) if sp.mirrored else (False,):
        m = model.mirrored() if mirrored else model
        f, b, t_out = _search_one(m, pyr, sp, mirrored, clock, stats)
        found += f
        timed_out |= t_out
        if b is not None and (low is None or b.score > low[0].score):
            low = (b, mirrored)
    u, v, w, h = model.roi
    min_dist = sp.min_distance_px if sp.min_distance_px is not None else min(w, h) / 3.0
    final, rejected = _verified(model, found, sp, min_dist, pyr)
    if sp.max_count is not None:
        final = final[:sp.max_count]
    best = None
    if low is not None:
        r, mir = low
        # the edge fit's pose (a hint of where the best candidate lay; not finished on the patch: a
        # grey-value fit of something that is not the part costs its most iterations and says nothing)
        fm = _match_of(r.pose, r, mir)
        best = Candidate(fm.u_px, fm.v_px, fm.angle_deg, r.score)
        if r.detail is not None and r.q is not None:
            lm = model.mirrored().levels[0] if mir else model.levels[0]
            lower = max(math.floor(r.score * 100) / 100, MIN_SCORE_FLOOR)  # the hint's min_score
            why = verify(lm, r.q, r.detail, r.grad_noise, lower, r.score, sp.min_surround).rejected_because
            best.verdict = why or "pass"
    if model.origin != (0.0, 0.0):
        final = [match_at_origin(model.origin, mt) for mt in final]
        for x in rejected:
            x.u_px, x.v_px = origin_at(model.origin, x.u_px, x.v_px, x.angle_deg, 1.0, x.mirrored)
        if best is not None and low is not None:
            best.u_px, best.v_px = origin_at(model.origin, best.u_px, best.v_px, best.angle_deg, low[0].pose.scale,
                                             low[1])
    stats["t_total_s"] = clock.elapsed()
    stats["cpu_total_s"] = clock.cpu()
    return FindResult(final, timed_out, clock.elapsed(), stats, best, sp.min_score, rejected)


def _verified(model: ShapeModel, found: list[Found], sp: SearchParams, min_dist: float, pyr: list[U8]
              ) -> tuple[list[Match], list[Rejected]]:
    """Final non-maximum suppression on level 0 with the verification (``verify``): the matches kept,
    best first, and the candidates that reached ``min_score`` but failed a check.

    A part and its mirror image compete too, and the mirror image must win by a margin (a
    mirror-symmetric part matches both ways). A candidate near a better match (closer than
    ``min_dist`` or its rectangle overlapping by more than ``max_overlap``) is the same instance; a
    candidate whose seen edges, less those on better matches' contours, score below ``min_score`` is
    a ghost made of their edges (two touching identical parts)."""
    found.sort(key=lambda t: -t[0].score + (MIRROR_MARGIN if t[0].mirrored else 0.0))
    final: list[Match] = []
    contours: list[Contour] = []
    rejected: list[Rejected] = []
    mirror = model.mirrored() if sp.mirrored else model
    levels = {False: model.levels[0], True: mirror.levels[0]}
    patches = {False: model.patch, True: mirror.patch}
    for mt, r in found:
        if any((mt.u_px - o.u_px) ** 2 + (mt.v_px - o.v_px) ** 2 < min_dist ** 2
               or overlap(model.roi, mt, o) > sp.max_overlap for o in final):
            continue
        if r.detail is None or r.q is None or r.n is None:
            final.append(mt)  # (not reached: every level-0 refinement carries its detail)
            continue
        vd = verify(levels[mt.mirrored], r.q, r.detail, r.grad_noise, sp.min_score, mt.score,
                    sp.min_surround, hidden_by(r.q, contours))
        why = vd.rejected_because
        if why is None:
            seen = (r.detail.agree > 0) & r.detail.visible
            mine = seen & ~claimed(r.q, r.n, seen, contours)
            unclaimed = float(r.detail.agree[mine].sum()) / max(mt.n_visible, 1)
            vd.scores["unclaimed"] = round(unclaimed, 4)
            if unclaimed < sp.min_score:
                why = (f"its edges are mostly those of better matches (unclaimed score {unclaimed:.2f} < "
                       f"min_score {sp.min_score:g}): a ghost between neighbouring parts")
        if why is None and model.colour is not None:  # a colour model's interior (vision.shape.colour)
            why = interior_verdict(patches[mt.mirrored], pyr, mt.u_px, mt.v_px, math.radians(mt.angle_deg),
                                   mt.scale, r.detail, vd.scores)
        mt.scores = {**vd.scores, **mt.scores}
        if why is None:
            final.append(_finish(patches[mt.mirrored], pyr, mt, r, model.view_cov()))
            contours.append(contour_of(r.q, r.n))
        elif all((mt.u_px - o.u_px) ** 2 + (mt.v_px - o.v_px) ** 2 >= min_dist ** 2 for o in rejected):
            rejected.append(Rejected(mt.u_px, mt.v_px, mt.angle_deg, mt.score, mt.mirrored, vd.scores, why))
    return final, rejected
