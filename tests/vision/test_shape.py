"""Shape-based matching on rendered scenes with known sub-pixel poses."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import pytest

from tests.support import pick_scenes as scenes
from vision import shape
from vision.types import FindResult, Match, SearchParams

SIZE = (640, 480)


def _style(**kw: object) -> scenes.SceneStyle:
    base: dict[str, object] = {"size": SIZE, "noise_sigma": 1.5, "clutter": 8}
    base.update(kw)
    return scenes.SceneStyle(**base)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def bracket() -> tuple[scenes.PartShape, shape.ShapeModel]:
    part = scenes.part_bracket()
    img, roi = scenes.teach_scene(part, np.random.default_rng(1), centre=(320.0, 240.0),
                                 style=_style(clutter=0))
    return part, shape.teach(img, roi)


def _one(part: scenes.PartShape, u: float, v: float, a: float, seed: int = 0,
         **style: object) -> tuple[np.ndarray, scenes.Truth]:
    img, truth = scenes.render([scenes.Instance(part, u, v, a)], _style(**style), np.random.default_rng(seed))
    return img, truth[0]


@pytest.mark.parametrize("angle", [0.0, 12.3, 37.5, 90.0, -90.0, -135.2, 179.6, -179.6, 180.0, -180.0])
def test_any_rotation_subpixel(bracket: tuple[scenes.PartShape, shape.ShapeModel], angle: float) -> None:
    part, model = bracket
    img, t = _one(part, 300.37, 231.81, angle, seed=int(abs(angle) * 10))
    res = shape.find(model, img)
    assert len(res.matches) == 1
    m = res.matches[0]
    assert abs(m.u_px - t.u_px) < 0.08 and abs(m.v_px - t.v_px) < 0.08
    assert abs(scenes.wrap_deg(m.angle_deg - t.angle_deg)) < 0.06
    assert -180.0 < m.angle_deg <= 180.0
    assert m.score > 0.85


def test_angle_sign_matches_getRotationMatrix2D(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    """Rotating the teach image with OpenCV by +30 deg must read as +30 deg about the reference point."""
    part, model = bracket
    img, roi = scenes.teach_scene(part, np.random.default_rng(5), centre=(320.0, 240.0), style=_style())
    ref = (roi[0] + roi[2] / 2, roi[1] + roi[3] / 2)
    M = cv2.getRotationMatrix2D(ref, 30.0, 1.0)
    M[:, 2] += (-25.5, 14.25)  # and move it by a known sub-pixel offset
    rotated = cv2.warpAffine(img, M, SIZE, flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    m = shape.find(model, rotated).matches[0]
    assert m.angle_deg == pytest.approx(30.0, abs=0.05)
    assert m.u_px == pytest.approx(ref[0] - 25.5, abs=0.08)
    assert m.v_px == pytest.approx(ref[1] + 14.25, abs=0.08)


def test_reference_point_is_roi_centre_not_part_origin() -> None:
    """An ROI off the part's origin: the match reports where the ROI centre went, rotated with the part."""
    part = scenes.part_bracket()
    img, (u, v, w, h) = scenes.teach_scene(part, np.random.default_rng(2), centre=(320.0, 240.0),
                                          style=_style(clutter=0))
    off = np.array([7.5, -4.25])  # reference point = part origin + off
    roi = (u + off[0], v + off[1], w, h)
    model = shape.teach(img, roi)
    for angle in (90.0, -160.0):
        scene, t = _one(part, 330.2, 250.6, angle, seed=3)
        m = shape.find(model, scene).matches[0]
        expect = np.array([t.u_px, t.v_px]) + scenes.rotation(angle) @ off
        assert m.u_px == pytest.approx(expect[0], abs=0.08)
        assert m.v_px == pytest.approx(expect[1], abs=0.08)
        assert scenes.wrap_deg(m.angle_deg - angle) == pytest.approx(0.0, abs=0.06)


def test_contrast_reversal_and_uneven_light(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    part, model = bracket
    img, t = _one(part, 350.6, 220.1, 63.0, background=190.0, part_value=60.0, light_gradient=0.6,
                  vignetting=0.3)
    m = shape.find(model, img).matches[0]
    assert math.hypot(m.u_px - t.u_px, m.v_px - t.v_px) < 0.1
    assert abs(scenes.wrap_deg(m.angle_deg - t.angle_deg)) < 0.08


def test_score_falls_smoothly_with_occlusion(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    part, model = bracket
    scores = []
    for occ in (0.0, 0.1, 0.2, 0.3):
        img, truth = scenes.render([scenes.Instance(part, 310.4, 245.3, -48.0, occ)], _style(),
                                  np.random.default_rng(11))
        ms = shape.find(model, img).matches
        assert len(ms) == 1, f"not found at {occ:.0%} occlusion"
        assert math.hypot(ms[0].u_px - truth[0].u_px, ms[0].v_px - truth[0].v_px) < 0.3
        scores.append(ms[0].score)
    assert all(a > b for a, b in zip(scores, scores[1:], strict=False))
    assert scores[-1] > 0.5 and scores[0] - scores[-1] > 0.15


def test_several_instances_best_first_with_max_count(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    part, model = bracket
    insts = [scenes.Instance(part, 150.3, 130.7, 10.0), scenes.Instance(part, 470.1, 140.2, -100.0, 0.25),
             scenes.Instance(part, 320.8, 350.4, 170.0)]
    img, truth = scenes.render(insts, _style(), np.random.default_rng(4))
    allm = shape.find(model, img).matches
    assert len(allm) == 3
    for t in truth:
        assert min(math.hypot(m.u_px - t.u_px, m.v_px - t.v_px) for m in allm) < 0.3
    assert [m.score for m in allm] == sorted((m.score for m in allm), reverse=True)
    two = shape.find(model, img, SearchParams(max_count=2)).matches
    assert len(two) == 2 and two[0].score == pytest.approx(allm[0].score)
    # the occluded one scores lowest
    assert math.hypot(allm[-1].u_px - 470.1, allm[-1].v_px - 140.2) < 0.5


def test_search_roi_and_angle_range(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    part, model = bracket
    insts = [scenes.Instance(part, 160.0, 240.0, 20.0), scenes.Instance(part, 480.0, 240.0, -120.0)]
    img, _ = scenes.render(insts, _style(), np.random.default_rng(6))
    left = shape.find(model, img, SearchParams(roi=(0, 0, 320, 480))).matches
    assert len(left) == 1 and abs(left[0].u_px - 160.0) < 0.3
    near20 = shape.find(model, img, SearchParams(angle_start_deg=0, angle_extent_deg=45)).matches
    assert len(near20) == 1 and abs(near20[0].angle_deg - 20.0) < 0.1


def test_nothing_in_an_empty_scene(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    _, model = bracket
    img, _ = scenes.render([], _style(clutter=30), np.random.default_rng(9))
    assert shape.find(model, img).matches == []


def test_timeout_returns_partial_result_with_flag(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    part, model = bracket
    insts = [scenes.Instance(part, 150.3, 130.7, 10.0), scenes.Instance(part, 470.1, 340.2, -100.0)]
    img, _ = scenes.render(insts, _style(), np.random.default_rng(4))
    full = shape.find(model, img, SearchParams(timeout_s=30.0))
    assert not full.timed_out and len(full.matches) == 2
    cut = shape.find(model, img, SearchParams(timeout_s=0.0))
    assert cut.timed_out
    assert len(cut.matches) < 2
    for m in cut.matches:  # whatever came back is a real, refined match
        assert min(math.hypot(m.u_px - f.u_px, m.v_px - f.v_px) for f in full.matches) < 1e-6


def test_teach_refuses_featureless_roi() -> None:
    img = np.full((100, 100), 128, np.uint8)
    with pytest.raises(ValueError, match="no edges"):
        shape.teach(img, (10, 10, 50, 50))


def test_high_min_score_keeps_clean_instances(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    """Coarse levels score lower than level 0; a high minimum must not lose a clean instance."""
    part, model = bracket
    insts = [scenes.Instance(part, 170.4, 160.3, 75.0), scenes.Instance(part, 450.2, 300.9, -20.0, 0.3)]
    img, _ = scenes.render(insts, _style(), np.random.default_rng(12))
    ms = shape.find(model, img, SearchParams(min_score=0.9)).matches
    assert len(ms) == 1 and abs(ms[0].u_px - 170.4) < 0.1 and ms[0].score >= 0.9


def _hits(res: FindResult, truth: list[tuple[float, float, float]], tol_px: float) -> int:
    return sum(any(math.hypot(m.u_px - u, m.v_px - v) < tol_px and abs(scenes.wrap_deg(m.angle_deg - a)) < 1.0
                   for m in res.matches) for u, v, a in truth)


def test_a_full_tray_of_identical_parts_is_found_whole(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    """30 identical parts: each is a cluster of top-level maxima, and the strongest clusters must
    not take every candidate (a fixed candidate list found 12-16 of them)."""
    part, model = bracket
    img, truth = scenes.tray_scene(part, np.random.default_rng(11))
    res = shape.find(model, img)
    assert _hits(res, [(t.u_px, t.v_px, t.angle_deg) for t in truth], 1.0) == 30
    assert len(res.matches) == 30


@pytest.mark.parametrize("k", [2, 4])
def test_a_tray_of_small_parts_is_found_whole(k: int) -> None:
    """The tray at 1/2 and 1/4 size: a model of 2 or 1 pyramid levels has no level to track on, its
    top-level candidates are settled on unspread responses first (from the spread plateaus' centres
    the refinement lost 3 of 120 parts at 1/2 and 15 of 120 at 1/4 over four trays)."""
    part = scenes.part_bracket()
    big_teach, (u, v, w, h) = scenes.teach_scene(part, np.random.default_rng(1008), centre=(640.3, 480.6),
                                                 style=_style(size=(1280, 960), clutter=0))
    small = lambda im: cv2.resize(im, None, fx=1 / k, fy=1 / k, interpolation=cv2.INTER_AREA)  # noqa: E731
    model = shape.teach(small(big_teach), scenes.roi_at_scale((u, v, w, h), k))
    assert model.top_level == {2: 2, 4: 1}[k]
    found = 0
    for seed in (5, 6):
        img, truth = scenes.tray_scene(part, np.random.default_rng(seed))
        res = shape.find(model, small(img))
        # pixel-centre convention: the centre of the top-left pixel is (0, 0) at every size
        found += _hits(res, [((t.u_px + 0.5) / k - 0.5, (t.v_px + 0.5) / k - 0.5, t.angle_deg) for t in truth], 2.0)
        assert len(res.matches) <= 30
    assert found == 60


def test_overlap_is_the_rectangles_intersection_over_the_smaller() -> None:
    """``overlap`` (with its early answer for far-apart rectangles) against the plain intersection."""
    from vision.shape.search import overlap

    roi = (0.0, 0.0, 60.0, 24.0)
    rng = np.random.default_rng(4)

    def plain(a: Match, b: Match) -> float:
        ra = ((a.u_px, a.v_px), (60 * a.scale, 24 * a.scale), -a.angle_deg)
        rb = ((b.u_px, b.v_px), (60 * b.scale, 24 * b.scale), -b.angle_deg)
        kind, pts = cv2.rotatedRectangleIntersection(ra, rb)
        if kind == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
            return 0.0
        return float(cv2.contourArea(cv2.convexHull(pts))) / min(ra[1][0] * ra[1][1], rb[1][0] * rb[1][1])

    def match(u: float, v: float, a: float, s: float) -> Match:
        return Match(u, v, a, 0.9, 0.1, s, False, 10, 10)

    touching = 0
    for _ in range(400):
        a = match(100.0, 100.0, float(rng.uniform(-180, 180)), float(rng.uniform(0.9, 1.1)))
        b = match(100.0 + rng.uniform(-70, 70), 100.0 + rng.uniform(-70, 70), float(rng.uniform(-180, 180)),
                  float(rng.uniform(0.9, 1.1)))
        assert overlap(roi, a, b) == pytest.approx(plain(a, b), abs=1e-12)
        touching += plain(a, b) > 0
    assert 50 < touching < 350  # both answers were exercised
    assert overlap(roi, match(0, 0, 0, 1), match(0, 0, 0, 1)) == pytest.approx(1.0)


def test_a_level_zero_fit_reads_its_1_sigma_from_its_covariance(bracket: tuple[scenes.PartShape, shape.ShapeModel]
                                                                 ) -> None:
    """``Refined.sigma_deg``/``sigma_px`` are the level-0 fit's honest covariance's (computed when read), NaN
    without one."""
    import math as m_

    from vision.image import pyramid
    from vision.shape.model import GRAD_PER_CONTRAST
    from vision.shape.refine import Pose, Refined, refine_lsq
    from vision.shape.uncertainty import sigma_of

    part, model = bracket
    assert model.origin == (0.0, 0.0)  # a match's position is the ROI centre's, where the fit starts
    img, _ = _one(part, 300.37, 231.81, 21.0, seed=5)
    pyr = pyramid(img, model.top_level + 1)
    # the level-0 edge fit, started a pixel and half a degree off the answer
    best = shape.find(model, img).matches[0]
    x, y = best.u_px, best.v_px
    r = refine_lsq(pyr[0], model.levels[0], Pose(x + 0.8, y - 0.6, m_.radians(best.angle_deg + 0.5), 1.0, 1.0),
                   model.params.edge_sigma_px, model.params.min_contrast * GRAD_PER_CONTRAST, 2.0, 5, fine=pyr[0],
                   min_contrast=model.params.min_contrast, perspective=True)
    assert r.cov is not None and np.all(np.isfinite(r.cov))
    assert (r.sigma_deg, r.sigma_px) == sigma_of(r.cov)
    assert 0.0 < r.sigma_deg < 0.1 and 0.0 < r.sigma_px < 0.1
    assert m_.isnan(Refined(r.pose, r.score, r.rms_px).sigma_deg)


def test_level_zero_extras_below_extras_from_are_computed_when_read(
        bracket: tuple[scenes.PartShape, shape.ShapeModel], monkeypatch: pytest.MonkeyPatch) -> None:
    """A level-0 fit scoring below ``extras_from`` computes its covariance and the crop's noise only when
    they are read (a search's hypotheses below min_score never read them), to the same bits as at once."""
    import math as m_

    from vision.image import pyramid
    from vision.shape import refine
    from vision.shape.model import GRAD_PER_CONTRAST

    part, model = bracket
    img, _ = _one(part, 300.37, 231.81, 21.0, seed=5)
    pyr = pyramid(img, model.top_level + 1)
    best = shape.find(model, img).matches[0]
    calls: list[str] = []
    real_cov, real_noise = refine.edge_cov, refine.grad_noise

    def cov(*a: Any) -> Any:
        calls.append("cov")
        return real_cov(*a)

    def noise(*a: Any) -> Any:
        calls.append("noise")
        return real_noise(*a)

    monkeypatch.setattr(refine, "edge_cov", cov)
    monkeypatch.setattr(refine, "grad_noise", noise)

    def fit(extras_from: float) -> refine.Refined:
        return refine.refine_lsq(pyr[0], model.levels[0], refine.Pose(best.u_px + 0.8, best.v_px - 0.6,
                                                                      m_.radians(best.angle_deg + 0.5), 1.0, 1.0),
                                 model.params.edge_sigma_px, model.params.min_contrast * GRAD_PER_CONTRAST, 2.0, 5,
                                 fine=pyr[0], min_contrast=model.params.min_contrast, perspective=True,
                                 extras_from=extras_from)

    now = fit(0.0)
    assert calls == ["cov", "noise"] and now.score > 0.9
    calls.clear()
    later = fit(1.01)  # above any score
    assert calls == []
    assert later.grad_noise == now.grad_noise and calls == ["noise"]
    assert later.cov is not None and now.cov is not None and np.array_equal(later.cov, now.cov)
    assert calls == ["noise", "cov"]
    assert later.cov is later.cov and calls == ["noise", "cov"]  # once
    assert (later.pose, later.score, later.rms_px) == (now.pose, now.score, now.rms_px)


def test_a_levels_fit_points_follow_its_features(bracket: tuple[scenes.PartShape, shape.ShapeModel]) -> None:
    """The fit points of a level's feature subset are cut once and kept with the level model; a level
    model whose features (or points) are replaced gets the new ones."""
    from dataclasses import replace

    from vision.shape.refine import _fit_points

    _, model = bracket
    lm = replace(model.levels[1])
    m1, n1 = _fit_points(lm, lm.features)
    assert m1.flags.c_contiguous and np.array_equal(m1, lm.points[lm.features])
    assert _fit_points(lm, lm.features)[0] is m1
    lm.features = lm.features[::2].copy()
    m2, n2 = _fit_points(lm, lm.features)
    assert np.array_equal(m2, lm.points[lm.features]) and np.array_equal(n2, lm.normals[lm.features])
    lm.points = lm.points + 1.0
    assert np.array_equal(_fit_points(lm, lm.features)[0], lm.points[lm.features])
