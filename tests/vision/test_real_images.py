"""The shape matcher on real photographs (``tests/data/pick_real``) and on hard variants of them.

Every dev case at the default settings: the instance count and the pose against the corpus's
``measured_estimate`` (``bench/pick_cases.py`` carries a match to the estimate's reference point).
Then parts cut by each image border, inverted contrast under each polarity option, a textured
background, mirror images, a scale range, degenerate images and settings that cannot work.
"""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from bench.pick_cases import (
    Case,
    Found,
    TestImage,
    faint,
    load_cases,
    read_grey,
    scaled,
    score,
    teach_model,
    teach_one,
    texture,
    to_reference,
    with_colour,
)
from vision import shape
from vision.errors import SettingsError
from vision.types import SearchParams

CASES = {c.id: c for c in load_cases()}
DEV = [(c, t) for c in CASES.values() for t in c.tests]

# Known misses (bench/results/pick_real.md): strict xfails, so a fix shows up as a pass to claim.
KNOWN_MISSES = {
    "robertson_screw_heads": "screw heads on wood grain: most of the default model is the teach head's glints, "
                             "socket and wood, and its best score anywhere near each head (an exhaustive grid of "
                             "position, angle and scale, bench/screw_heads.py) is 0.39-0.61, >= 0.5 on only 2 of 9 "
                             "heads: no search finds them at the defaults, the model would have to change. The heads "
                             "are not smaller than the taught one (radii by colour 47.3-49.4 px, taught 48.3); a model "
                             "of the long chains only (TeachParams(min_component_px=120)) finds 4 of 9 at 0.5 with 0 "
                             "false. The reason names the min_score that answers a head (bench/results/pick_real.md). "
                             "Taught from the teach image's four heads (more_teach_rois) 7 of 9 are found at the "
                             "defaults, 0.7-3.3 px from their rim centres (test_several_views_find_more_screw_heads, "
                             "test_screw_heads_report_their_rim_centre_with_an_honest_sigma); taught and searched on "
                             "the colour photos' chroma (TeachParams(colour='auto')) all 9, their rims measured "
                             "0.82 px RMS from the reference (test_screw_heads_in_colour_are_all_found_and_their_"
                             "rim_measured_to_a_pixel). This test keeps one ROI and the grey images (no colour "
                             "model)",
}


def _model(case_id: str) -> shape.ShapeModel:
    return teach_one(CASES[case_id])  # (a case with measured centres: reporting the first one)


_MODELS: dict[str, shape.ShapeModel] = {}


def model_of(case: Case) -> shape.ShapeModel:
    if case.id not in _MODELS:
        _MODELS[case.id] = _model(case.id)
    return _MODELS[case.id]


def _found(res: object) -> list[Found]:
    return [Found(m.u_px, m.v_px, m.angle_deg, m.score, m.mirrored) for m in res.matches]  # type: ignore[attr-defined]


def _params(case: Case, test: TestImage) -> list[object]:
    marks = []
    if case.id in KNOWN_MISSES and test.expected_count > 0:
        marks.append(pytest.mark.xfail(strict=True, reason=KNOWN_MISSES[case.id]))
    return [pytest.param(case, test, id=f"{case.id}-{test.path.name}", marks=marks)]


@pytest.mark.parametrize(("case", "test"), [p for c, t in DEV for p in _params(c, t)])
def test_dev_case_default_settings(case: Case, test: TestImage) -> None:
    res = shape.find(model_of(case), read_grey(test.path))
    s = score(case, test, _found(res))
    assert s.false == 0
    # the reverse-side key is a hard, optional instance (cases.yaml): it may be found by its outline,
    # which is nearly mirror-symmetric; every other instance must be
    optional = [i for i in test.instances if i.mirrored]
    assert test.expected_count - len(optional) <= s.found <= test.expected_count, res.reason()
    required = TestImage(test.path, test.expected_count - len(optional), [i for i in test.instances if not i.mirrored])
    r = score(case, required, [f for f in _found(res) if _near_any(case, f, required)])
    assert r.found == required.expected_count
    # within the 1 px / 1 deg target plus the estimate's own stated accuracy (it is no ground truth)
    assert r.out_of_tolerance == 0, (r.pos_err, r.ang_err)


def _near_any(case: Case, f: Found, test: TestImage) -> bool:
    gate = 0.5 * min(case.roi[2], case.roi[3])
    x, y = to_reference(case, f)
    return any(math.hypot(x - i.x, y - i.y) <= gate for i in test.instances)


@pytest.mark.xfail(strict=True, reason="the reverse-side key is another key of the same blank: other bitting "
                                       "(shallow cuts, square tip), other face (stamped 'HE 2', a shoulder ridge); "
                                       "its search scores 0.39 unmirrored; the mirrored model's best over +-16 px "
                                       "and the whole turn is 0.49, its bitting edge 0.20 (bench/key_reverse.py)")
def test_mirrored_key_found_with_mirrored_search() -> None:
    case = CASES["generalized_hough_keys"]
    test = case.tests[0]
    res = shape.find(model_of(case), read_grey(test.path), SearchParams(mirrored=True))
    s = score(case, test, _found(res))
    assert s.found == 2 and s.false == 0
    assert any(m.mirrored for m in res.matches)


def _plate() -> tuple[shape.ShapeModel, np.ndarray, tuple[float, float, float]]:
    """The back-lit plate's model and its teach image, with its pose found there."""
    case = CASES["sick_edgematcher_single"]
    img = case.teach_image()
    model = model_of(case)
    m = shape.find(model, img).matches[0]
    return model, img, (m.u_px, m.v_px, m.angle_deg)


def _shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    bg = float(np.median(img))
    M = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float32)
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderValue=bg)


@pytest.mark.parametrize(("dx", "dy"), [(-200, 0), (200, 0), (0, -150), (0, 150)],
                         ids=["left", "right", "top", "bottom"])
def test_part_cut_by_each_border_is_found(dx: float, dy: float) -> None:
    model, img, (u, v, a) = _plate()
    res = shape.find(model, _shift(img, dx, dy))
    assert len(res.matches) == 1, res.reason()
    m = res.matches[0]
    assert math.hypot(m.u_px - (u + dx), m.v_px - (v + dy)) < 1.0
    assert abs(m.angle_deg - a) < 0.5
    assert m.n_visible < len(model.levels[0].points)  # scored on the visible points only


@pytest.mark.parametrize(("dx", "dy"), [(-520, 0), (0, 420), (-480, -380)])
def test_part_mostly_outside_never_crashes(dx: float, dy: float) -> None:
    """A sliver of the part at the border: found at the right place, or skipped."""
    model, img, (u, v, _) = _plate()
    res = shape.find(model, _shift(img, dx, dy))
    for m in res.matches:
        assert math.hypot(m.u_px - (u + dx), m.v_px - (v + dy)) < 2.0


@pytest.fixture(scope="module")
def multi() -> tuple[Case, TestImage, np.ndarray]:
    case = CASES["sick_edgematcher_multi"]
    return case, case.tests[0], read_grey(case.tests[0].path)


@pytest.mark.parametrize(("polarity", "expect_inverted"), [("use_polarity", 0), ("ignore_global_polarity", 7),
                                                          ("ignore_local_polarity", 7)])
def test_inverted_contrast_per_polarity_option(multi: tuple[Case, TestImage, np.ndarray], polarity: str,
                                               expect_inverted: int) -> None:
    case, test, img = multi
    sp = SearchParams(polarity=polarity)  # type: ignore[arg-type]
    direct = score(case, test, _found(shape.find(model_of(case), img, sp)))
    assert direct.found == 7 and direct.false == 0
    inv = score(case, test, _found(shape.find(model_of(case), 255 - img, sp)))
    assert inv.found == expect_inverted and inv.false == 0


def test_texture_heavy_background(multi: tuple[Case, TestImage, np.ndarray]) -> None:
    case, test, img = multi
    s = score(case, test, _found(shape.find(model_of(case), texture(img))))
    assert s.found == 7 and s.false == 0 and s.out_of_tolerance == 0


@pytest.mark.parametrize("case_id", ["sick_edgematcher_multi", "invariant_tm_shaft_supports", "generalized_hough_keys"])
def test_faint_blurred_noisy_view(case_id: str) -> None:
    """Contrast cut to a quarter, blur 2.5 px, noise 2 grey levels: the edges fall below the taught
    contrast, and the find-time threshold follows the part down (above the image's noise)."""
    case = CASES[case_id]
    test = case.tests[0]
    res = shape.find(model_of(case), faint(read_grey(test.path)))
    required = TestImage(test.path, sum(1 for i in test.instances if not i.mirrored),
                         [i for i in test.instances if not i.mirrored])
    s = score(case, required, [f for f in _found(res) if _near_any(case, f, required)])
    assert s.found == required.expected_count, res.reason()
    assert s.out_of_tolerance == 0, (s.pos_err, s.ang_err)
    assert score(case, test, _found(res)).false == 0


@pytest.mark.parametrize("k", [0.5, 0.25])
def test_small_parts(k: float) -> None:
    """The back-lit double crosses with teach and test images resized (43 x 26 px, then 21 x 13 px):
    the pyramid stays shallow enough to keep the part, and every instance is found."""
    case = scaled(CASES["sick_edgematcher_multi"], k)
    model = shape.teach(case.teach_image(), case.roi)
    for test in case.tests:
        s = score(case, test, _found(shape.find(model, case.test_image(test))))
        assert s.found == test.expected_count and s.false == 0
        assert s.out_of_tolerance == 0, (s.pos_err, s.ang_err)


def test_mirror_image_of_an_asymmetric_part() -> None:
    case = CASES["sick_edgematcher_single"]
    test = case.tests[0]
    img = read_grey(test.path)
    flipped = np.ascontiguousarray(img[:, ::-1])
    model = model_of(case)
    unmirrored = shape.find(model, flipped).matches  # the outline alone fits a turned plate, partly
    res = shape.find(model, flipped, SearchParams(mirrored=True))
    assert len(res.matches) == 1 and res.matches[0].mirrored
    assert all(m.score < res.matches[0].score - 0.2 for m in unmirrored)
    direct = shape.find(model, img).matches[0]
    m = res.matches[0]
    assert m.u_px == pytest.approx(img.shape[1] - 1 - direct.u_px, abs=1.0)
    assert m.v_px == pytest.approx(direct.v_px, abs=1.0)


def test_scale_range_finds_a_larger_part() -> None:
    model, img, (u, v, _) = _plate()
    c = (float(u), float(v))
    M = cv2.getRotationMatrix2D(c, 20.0, 1.18)
    big = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                         borderValue=float(np.median(img)))
    res = shape.find(model, big, SearchParams(scale_min=0.9, scale_max=1.25))
    assert len(res.matches) == 1, res.reason()
    m = res.matches[0]
    assert m.scale == pytest.approx(1.18, abs=0.01)
    assert m.angle_deg == pytest.approx(20.0, abs=0.3)
    assert math.hypot(m.u_px - u, m.v_px - v) < 1.0


def test_matches_report_agreeing_model_points() -> None:
    case = CASES["sick_edgematcher_single"]
    res = shape.find(model_of(case), read_grey(case.tests[0].path))
    m = res.matches[0]
    n = len(model_of(case).levels[0].points)
    assert m.n_visible == n
    assert 0.8 * n <= m.n_points <= n


@pytest.mark.parametrize("img", [np.zeros((0, 0), np.uint8), np.zeros((480, 640), np.uint8),
                                 np.full((480, 640), 200, np.uint8), np.full((5, 7), 9, np.uint8),
                                 np.zeros((480, 640, 3), np.uint8)],
                         ids=["empty", "black", "constant", "tiny", "colour-black"])
def test_empty_and_constant_images_answer_no_match(img: np.ndarray) -> None:
    res = shape.find(model_of(CASES["sick_edgematcher_multi"]), img, SearchParams(mirrored=True))
    assert res.matches == []
    assert res.reason()


@pytest.mark.parametrize(("kw", "says"), [
    ({"min_score": 1e-9}, "min_score"), ({"min_score": float("nan")}, "min_score"), ({"min_score": 1.5}, "min_score"),
    ({"max_count": 0}, "max_count"), ({"max_count": -3}, "max_count"),
    ({"angle_extent_deg": 0.0}, "angle_extent_deg"), ({"angle_extent_deg": 720.0}, "angle_extent_deg"),
    ({"angle_start_deg": float("inf")}, "angle_start_deg"), ({"roi": (0, 0, 0, 10)}, "roi"),
    ({"polarity": "both"}, "polarity"), ({"greediness": 2.0}, "greediness"),
    ({"scale_min": 1.1, "scale_max": 1.2}, "scale"), ({"max_overlap": -0.1}, "max_overlap"),
    ({"timeout_s": -1.0}, "timeout_s"), ({"min_surround": 1.5}, "min_surround"),
    ({"min_surround": float("nan")}, "min_surround"),
])
def test_absurd_settings_are_refused_by_the_matcher(kw: dict[str, object], says: str) -> None:
    with pytest.raises(SettingsError, match=says):
        SearchParams(**kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("test", [t for t in CASES["robertson_screw_heads"].tests if t.expected_count],
                         ids=lambda t: t.path.name)
def test_a_part_missed_at_the_defaults_gets_a_reason_naming_the_setting(test: TestImage) -> None:
    """Where the screw heads are not found, the reason (what the annotated frame shows) names the
    min_score at which the best candidate would be answered, or why a lower one would not."""
    res = shape.find(model_of(CASES["robertson_screw_heads"]), read_grey(test.path))
    if res.matches:
        return  # found: nothing to explain
    reason = str(res.reason())
    assert "min_score" in reason
    assert "would be answered (it passes the verification)" in reason or "would not answer it either" in reason
    named = re.search(r"at min_score ([0-9.]+) it would be answered", reason)
    if named:
        # the setting named finds a screw head, and nothing that is not one
        case = CASES["robertson_screw_heads"]
        again = shape.find(model_of(case), read_grey(test.path), SearchParams(min_score=float(named.group(1))))
        s = score(case, test, _found(again))
        assert s.found >= 1 and s.false == 0, (reason, s)


def test_small_screw_heads_sparse_on_one_side_are_not_taken_for_pieces() -> None:
    """At a quarter size (heads ~25 px across) the screw heads' fits are sparse: a head whose every
    chain is at least half seen may still have its seen points on one side (surround 0.16 on one
    head of 100_1001.jpg). It lacks no piece, so the surround check does not judge it: the heads found
    before that check are found, with no false match."""
    case = scaled(CASES["robertson_screw_heads"], 0.25)
    model = teach_one(case)
    found = false = 0
    for test in case.tests:
        res = shape.find(model, case.test_image(test))
        s = score(case, test, _found(res))
        found, false = found + s.found, false + s.false
        assert not [r for r in res.rejected if "min_surround" in r.reason and r.scores["coverage"] > 0.95]
    assert found == 9 and false == 0  # every head (8 with the check judging the sparse one)


def test_dev_instances_against_the_swept_reference() -> None:
    """Every found dev instance with an angle lies within 1 px and 1 deg of a reference — the NCC sweep
    of the taught patch (``bench/pick_reference.py``) or the corpus's estimate, whichever agrees
    better (each is off by up to ~0.8 px where the other is right) — and the reported 1-sigma is
    honest: actual / reported against the sweep, its own error (measured on renders) in quadrature,
    has an RMS within 0.5-2 over all of them and case by case (issue 37)."""
    from bench.pick_instances import instance_rows
    from bench.pick_reference import REF_SIGMA

    ratios_px: list[float] = []
    ratios_deg: list[float] = []
    per_case: dict[str, list[tuple[float, float]]] = {}
    for case, test in DEV:
        if case.id == "robertson_screw_heads":
            continue
        img = read_grey(test.path)
        res = shape.find(model_of(case), img)
        rows = instance_rows(case, test, img, res.matches)
        s = score(case, test, _found(res))
        for row in rows:
            if row.err is None:
                continue
            near_ref = row.err[0] <= 1.0 and abs(row.err[1]) <= 1.0
            near_est = max(s.pos_err, default=0.0) <= 1.5 and max(map(abs, s.ang_err), default=0.0) <= 1.0
            assert near_ref or near_est, (row.image, row.err, s.pos_err, s.ang_err)
            ratios_px.append(row.err[0] / math.hypot(row.sigma[0], REF_SIGMA[0]))
            ratios_deg.append(abs(row.err[1]) / math.hypot(row.sigma[1], REF_SIGMA[1]))
            per_case.setdefault(case.id, []).append((ratios_px[-1], ratios_deg[-1]))
    assert len(ratios_px) >= 22
    rms_px = math.sqrt(sum(r * r for r in ratios_px) / len(ratios_px))
    rms_deg = math.sqrt(sum(r * r for r in ratios_deg) / len(ratios_deg))
    assert 0.5 <= rms_px <= 2.0 and 0.5 <= rms_deg <= 2.0, (rms_px, rms_deg)
    # case by case too (issue 37 round 4): a turned 3-D block whose edge fit and patch fit disagree by
    # 1.4 px reports about half a pixel (uncertainty.merge), not a quarter
    for cid, rs in per_case.items():
        for k in (0, 1):
            rms = math.sqrt(sum(r[k] ** 2 for r in rs) / len(rs))
            assert 0.5 <= rms <= 2.0, (cid, "position" if k == 0 else "angle", rms)


def test_several_views_find_more_screw_heads() -> None:
    """The screw heads taught from the teach image's four heads (``more_teach_rois``: the edges most heads
    share with the same contrast polarity, their average patch) are found where the one-head model finds
    none, and nothing else is: the empty holes of the four photos stay unmatched (bench/results/pick_real.md:
    7 of 9, 0 false in every variant and size)."""
    case = CASES["robertson_screw_heads"]
    many = teach_model(case)
    found_one = found_many = 0
    for test in case.tests:
        img = read_grey(test.path)
        one = score(case, test, _found(shape.find(model_of(case), img)))
        s = score(case, test, _found(shape.find(many, img)))
        assert s.false == 0 and one.false == 0
        found_one += one.found
        found_many += s.found
    assert found_one == 0
    assert found_many >= 6


def test_screw_heads_report_their_rim_centre_with_an_honest_sigma() -> None:
    """The model taught from the teach image's four heads reports the heads' centre (``teach_centres``:
    each teach head's rim, ``bench/screw_rim.py``; their mean in the part's frame, ``ShapeModel.origin``)
    and a 1-sigma that holds how far that centre moves from view to view: against the rim reference
    (the corpus's ``measured_estimate``) the found heads lie 0.7-3.3 px off (RMS 2.05 px), and
    actual / reported is honest (RMS 0.85, per head 0.24-1.40; target 0.5-2). The 1 px target is missed
    (bench/results/pick_real.md)."""
    case = CASES["robertson_screw_heads"]
    model = teach_model(case)
    assert model.origin != (0.0, 0.0)
    ratios = []
    for test in case.tests:
        res = shape.find(model, read_grey(test.path))
        for i in test.instances:
            near = [m for m in res.matches if math.hypot(m.u_px - i.x, m.v_px - i.y) < 30]
            if near:
                m = min(near, key=lambda m: math.hypot(m.u_px - i.x, m.v_px - i.y))
                err = math.hypot(m.u_px - i.x, m.v_px - i.y)
                assert err < 4.0, (test.path.name, i, err)
                ratios.append(err / (math.sqrt(2) * m.sigma_px))
    assert len(ratios) >= 6
    rms = math.sqrt(sum(r * r for r in ratios) / len(ratios))
    assert 0.5 <= rms <= 2.0, ratios



def test_screw_heads_in_colour_are_all_found_and_their_rim_measured_to_a_pixel() -> None:
    """The screw heads taught from the teach image's four heads on a chroma channel of the colour photos
    (``TeachParams(colour="auto")``, ``vision.shape.colour``: the head against the wood with the wood's own
    colour, and so its shading, projected out) are all found, nothing else is, and the rim measured after
    each match (``vision.shape.rim``) lies within a pixel of the rim reference in RMS (0.82 px; 8 of 9
    within 0.55 px) with an honest 1-sigma (actual / reported RMS 1.59; target 0.5-2). The reference is
    itself a circle fit to colour edges (method A of ``bench/screw_rim.py``; the independent method B is
    1.65 px RMS away, as far as A is from B): bench/results/pick_real.md."""
    from vision.shape.rim import rim_centre

    case = with_colour(CASES["robertson_screw_heads"], "auto")
    assert case.colour
    model = teach_model(case)
    assert model.colour is not None
    errs, ratios = [], []
    for test in case.tests:
        img = case.test_image(test)
        assert img.ndim == 3
        res = shape.find(model, img)
        s = score(case, test, _found(res))
        assert s.false == 0 and s.found == len(test.instances), test.path.name
        for i in test.instances:
            m = min(res.matches, key=lambda m: math.hypot(m.u_px - i.x, m.v_px - i.y))
            fit = rim_centre(model, img, m)
            assert fit is not None
            errs.append(math.hypot(fit.u_px - i.x, fit.v_px - i.y))
            ratios.append(errs[-1] / (math.sqrt(2) * fit.sigma_px))
    assert len(errs) == 9
    assert math.sqrt(float(np.mean(np.square(errs)))) < 1.0, errs
    assert max(errs) < 3.0, errs
    assert 0.5 <= math.sqrt(float(np.mean(np.square(ratios)))) <= 2.0, ratios
