"""The point a match reports (``vision.shape.frame``: ``ShapeModel.origin``) and the screw heads' rim
reference it is measured with (``bench/screw_rim.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support import pick_scenes
from vision import shape
from vision.errors import TeachError
from vision.shape.frame import part_centre, recentred
from vision.shape.model import ShapeModel
from vision.shape.multi import teach_many

SIZE = (640, 480)


def _scene(angle_deg: float, seed: int) -> tuple[np.ndarray, pick_scenes.Truth]:
    part = pick_scenes.part_bracket()
    img, truth = pick_scenes.render([pick_scenes.Instance(part, 300.4, 240.8, angle_deg)],
                                    pick_scenes.SceneStyle(size=SIZE, noise_sigma=2.0, clutter=10),
                                    np.random.default_rng(seed))
    return img, truth[0]


def _model() -> ShapeModel:
    img, roi = pick_scenes.teach_scene(pick_scenes.part_bracket(), np.random.default_rng(40), centre=(320.3, 240.6),
                                       style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
    return shape.teach(img, roi)


def test_a_recentred_model_reports_its_origin_and_searches_as_taught() -> None:
    model = _model()
    moved = recentred(model, 7.0, -4.0)
    for angle, seed in ((0.0, 1), (33.3, 2), (-120.0, 3)):
        img, truth = _scene(angle, seed)
        a, b = shape.find(model, img), shape.find(moved, img)
        assert len(a.matches) == len(b.matches) == 1
        ma, mb = a.matches[0], b.matches[0]
        t = math.radians(ma.angle_deg)
        k = ma.scale  # (the fit's apparent size: ~1 here)
        want = (ma.u_px + k * (math.cos(t) * 7.0 + math.sin(t) * -4.0),
                ma.v_px + k * (-math.sin(t) * 7.0 + math.cos(t) * -4.0))
        assert math.hypot(mb.u_px - want[0], mb.v_px - want[1]) < 1e-9
        assert (mb.angle_deg, mb.score) == pytest.approx((ma.angle_deg, ma.score), abs=1e-9)
        # the contour drawn at the reported point is the part's, wherever the origin lies
        assert np.allclose(moved.contour(mb.u_px, mb.v_px, mb.angle_deg, mb.scale)[0],
                           model.contour(ma.u_px, ma.v_px, ma.angle_deg, ma.scale)[0])
        # the reported point's 1-sigma carries the turn's over the arm of the origin (never smaller)
        assert mb.sigma_px >= ma.sigma_px
        assert math.hypot(ma.u_px - truth.u_px, ma.v_px - truth.v_px) < 0.1
    # kept in the model file, and mirrored about the ROI centre with the model
    again = ShapeModel.from_dict(moved.to_dict(), moved.params, moved.roi, moved.image_size)
    assert again.origin == (7.0, -4.0)
    assert moved.mirrored().origin == (-7.0, -4.0)
    assert "origin_px" not in model.to_dict()
    with pytest.raises(TeachError, match="finite"):
        recentred(model, float("nan"), 0.0)


def test_the_part_centre_of_several_views_is_their_mean_in_the_parts_frame() -> None:
    # two views: the part turned 90 deg CCW in the second; the centre measured 1 px apart in the part frame
    poses = [(100.0, 100.0, 0.0, 1.0), (300.0, 200.0, math.pi / 2, 1.0)]
    # part-frame (3, 2) in view 1; part-frame (3, 4) in view 2: model -> image R = [[c, s], [-s, c]]
    centres = [(103.0, 102.0), (300.0 + 4.0, 200.0 - 3.0)]
    assert part_centre(poses, centres) == pytest.approx((3.0, 3.0))
    with pytest.raises(TeachError, match="one measured centre per teach view"):
        part_centre(poses, centres[:1])


def test_teach_many_with_centres_reports_the_measured_centre() -> None:
    imgs, rois = [], []
    for k, centre in enumerate([(320.3, 240.6), (300.7, 250.2)]):
        img, roi = pick_scenes.teach_scene(pick_scenes.part_bracket(), np.random.default_rng(40 + k), centre=centre,
                                           style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
        imgs.append(img)
        rois.append(roi)
    # a point 5 px right and 3 px below each view's ROI centre (the parts are drawn unturned there)
    centres = [(u + w / 2 + 5.0, v + h / 2 + 3.0) for u, v, w, h in rois]
    plain = teach_many(imgs, rois)
    model = teach_many(imgs, rois, centres=centres)
    assert model.origin == pytest.approx((5.0, 3.0), abs=0.1)
    one = teach_many(imgs[:1], rois[:1], centres=centres[:1])
    assert one.origin == pytest.approx((5.0, 3.0), abs=1e-9)
    img, truth = _scene(33.3, 5)
    mp, mm = shape.find(plain, img).matches[0], shape.find(model, img).matches[0]
    t = math.radians(truth.angle_deg)
    want = (truth.u_px + math.cos(t) * 5.0 + math.sin(t) * 3.0, truth.v_px - math.sin(t) * 5.0 + math.cos(t) * 3.0)
    assert math.hypot(mm.u_px - want[0], mm.v_px - want[1]) < 0.15
    assert (mm.score, mm.angle_deg) == pytest.approx((mp.score, mp.angle_deg), abs=1e-9)
    with pytest.raises(TeachError, match="one centre per teach image"):
        teach_many(imgs, rois, centres=centres[:1])


def test_the_rim_reference_is_good_to_half_a_pixel_on_rendered_heads() -> None:
    """``bench/screw_rim.py``'s two measures of a screw head's centre (the rim circle of the colour
    saturation's edge; the centre of polar symmetry) on rendered heads with a one-sided shadow, a light
    gradient, noise and JPEG, started 3 px off: both within 0.7 px (the rim circle's own 1-sigma,
    0.05-0.3 px, does not hold the shadow's pull of up to half a pixel: bench/results/pick_real.md)."""
    from bench.screw_rim import render_head, rim_circle, symmetry_centre

    rng = np.random.default_rng(8)
    for _ in range(4):
        img, cx, cy, r = render_head(rng)
        ax, ay, ar, sig, _ = rim_circle(img, cx + 2.1, cy - 2.1, r * 1.08)
        bx, by = symmetry_centre(img, ax, ay, ar)
        ea, eb = math.hypot(ax - cx, ay - cy), math.hypot(bx - cx, by - cy)
        assert ea < 0.7 and eb < 0.7, (ea, eb)
        assert abs(ar - r) < 0.7
        assert sig > 0


def test_a_part_lying_face_down_reports_the_mirrored_origin() -> None:
    """A mirrored match (``SearchParams(mirrored=True)``) reports the origin mirrored with the part: the
    point 7 px to the part's right when face up is 7 px to its left when face down."""
    from vision.types import SearchParams

    model = recentred(_model(), 7.0, -4.0)
    flipped = pick_scenes.mirrored_part(pick_scenes.part_bracket())
    img, truth = pick_scenes.render([pick_scenes.Instance(flipped, 300.4, 240.8, 20.0)],
                                    pick_scenes.SceneStyle(size=SIZE, noise_sigma=2.0, clutter=0),
                                    np.random.default_rng(9))
    got = shape.find(model, img, SearchParams(mirrored=True)).matches
    assert len(got) == 1 and got[0].mirrored
    t = math.radians(got[0].angle_deg)
    want = (truth[0].u_px + math.cos(t) * -7.0 + math.sin(t) * -4.0,
            truth[0].v_px - math.sin(t) * -7.0 + math.cos(t) * -4.0)
    assert math.hypot(got[0].u_px - want[0], got[0].v_px - want[1]) < 0.15
    # and the contour drawn at it is the one the model as taught draws at its own match
    plain = shape.find(_model(), img, SearchParams(mirrored=True)).matches[0]
    pts, _ = model.contour(got[0].u_px, got[0].v_px, got[0].angle_deg, got[0].scale, mirrored=True)
    ref, _ = _model().contour(plain.u_px, plain.v_px, plain.angle_deg, plain.scale, mirrored=True)
    assert np.allclose(pts, ref, atol=1e-6)
