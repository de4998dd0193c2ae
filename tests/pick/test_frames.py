"""The annotated frame: each match's model contour at its pose, and the reason when nothing is found."""

from __future__ import annotations

import functools

import numpy as np

from bench.pick_cases import load_cases, read_grey
from cellctl.pick.frames import FrameCache, annotate, match_contours
from cellctl.pick.model import PartModel, teach
from vision.types import SearchParams

CONTOUR = np.array([0, 255, 255])


@functools.cache
def _plate() -> tuple[PartModel, np.ndarray]:
    """The taught plate and its first test image (taught once per process: no test changes either)."""
    case = next(c for c in load_cases() if c.id == "sick_edgematcher_single")
    return teach(case.teach_image(), case.roi, name="plate"), read_grey(case.tests[0].path)


def test_contour_drawn_at_the_match_pose() -> None:
    model, img = _plate()
    res = model.find(img)
    matches = [{**m.as_dict(), "part": "plate", "reachable": True} for m in res.matches]
    contours = match_contours([model], matches)
    cache = FrameCache()
    fid = cache.add(img, matches, contours, res.reason())
    out = annotate(cache.get(fid))
    seg = contours[0]
    assert len(seg) == len(model.shape.levels[0].points)  # type: ignore[union-attr]
    mid = np.rint(seg.mean(axis=1)).astype(int)
    inside = (mid[:, 0] >= 0) & (mid[:, 1] >= 0) & (mid[:, 0] < img.shape[1]) & (mid[:, 1] < img.shape[0])
    px = out[mid[inside, 1], mid[inside, 0]].astype(int)
    yellowish = (px[:, 1] > 150) & (px[:, 2] > 150) & (px[:, 0] < 120)
    assert yellowish.mean() > 0.8  # the contour lies on the part's edges as the match places them
    # and it moved with the part: the same contour at the teach pose misses most of them
    shifted = model.contour(model.reference_px[0], model.reference_px[1], 0.0)
    assert np.abs(shifted.mean(axis=(0, 1)) - seg.mean(axis=(0, 1))).max() > 3.0


def test_reason_shown_when_nothing_found() -> None:
    model, img = _plate()
    blank = np.full_like(img, int(np.median(img)))
    res = model.find(blank)
    assert res.matches == [] and res.reason()
    cache = FrameCache()
    out = annotate(cache.get(cache.add(blank, [], [], res.reason())))
    band = out[:30].astype(int)
    assert (band[..., 2] > 150).any()  # the text is drawn (orange on a darkened band)
    assert band.mean() < 0.6 * blank.mean()


def test_reason_names_the_best_candidate_below_min_score() -> None:
    model, img = _plate()
    best = model.find(img).matches[0]
    res = model.find(img, SearchParams(min_score=min(1.0, best.score + 0.01)))
    assert res.matches == []
    text = res.reason() or ""
    assert text.startswith("best candidate scored ") and "< min_score" in text
    assert f"({best.u_px:.1f}, {best.v_px:.1f})" in text
