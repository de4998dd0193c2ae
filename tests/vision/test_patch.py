"""The taught patch (``vision.shape.patch``): the part's interior finishes the pose and its 1-sigma.

A round part whose turn only its interior shows (smooth shading marks, no edge above the model's
contrast): the outline fixes the position, the patch the angle; the 1-sigma says what the data allow.
A model file keeps the patch; a file without one finds with the edge fit alone.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vision import shape
from vision.errors import TeachError
from vision.shape.model import ShapeModel
from vision.shape.patch import patch_from_dict, patch_to_dict
from vision.shape.uncertainty import classical, combine, honest_cov, jackknife, merge

SS = 8  # supersampling of the renders


def _disc(cx: float, cy: float, angle_deg: float, seed: int, size: tuple[int, int] = (640, 480)) -> np.ndarray:
    """A bright disc (radius 70 px) on a dark ground with two soft marks inside at a turn of
    ``angle_deg`` (CCW on screen) about its centre; the marks' gradients stay below 3 grey/px."""
    w, h = size
    yy, xx = np.mgrid[0:h * SS, 0:w * SS].astype(np.float32)
    X, Y = (xx + 0.5) / SS - 0.5 - cx, (yy + 0.5) / SS - 0.5 - cy
    a = math.radians(angle_deg)
    # the part's own frame: a point at the part's (px, py) lies at R(a) (px, py) on screen
    px, py = math.cos(a) * X - math.sin(a) * Y, math.sin(a) * X + math.cos(a) * Y
    img = np.full((h * SS, w * SS), 60.0, np.float32)
    inside = X * X + Y * Y <= 70.0 ** 2
    mark = 40 * np.exp(-((px - 35) ** 2 + py ** 2) / (2 * 12.0 ** 2)) \
        - 30 * np.exp(-((px + 10) ** 2 + (py - 38) ** 2) / (2 * 10.0 ** 2))
    img = np.where(inside, 150.0 + mark, img)
    small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 0.7)
    rng = np.random.default_rng(seed)
    return np.clip(small + rng.normal(0, 2.0, small.shape), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def disc_model() -> ShapeModel:
    return shape.teach(_disc(320.0, 240.0, 0.0, 1), (230, 150, 180, 180))


@pytest.mark.parametrize("angle", [67.3, -141.8])
def test_the_interior_fixes_the_turn_of_a_round_part(disc_model: ShapeModel, angle: float) -> None:
    img = _disc(400.3, 250.7, angle, 7)
    res = shape.find(disc_model, img)
    assert len(res.matches) == 1, res.reason()
    m = res.matches[0]
    assert math.hypot(m.u_px - 400.3, m.v_px - 250.7) < 0.3
    err = abs((m.angle_deg - angle + 180) % 360 - 180)
    assert err < 1.0, (m.angle_deg, angle)
    # the 1-sigma is what the soft marks allow: neither the outline's hundredth nor meaningless
    assert 0.005 < m.sigma_angle_deg < 2.0
    assert m.scores["patch_ncc"] > 0.9
    # the edges alone cannot tell the turn: the same search without the patch is off
    bare = ShapeModel(disc_model.levels, disc_model.params, disc_model.roi, disc_model.image_size, None)
    mb = shape.find(bare, img).matches[0]
    assert abs((mb.angle_deg - angle + 180) % 360 - 180) > 5.0


def test_patch_round_trip_and_a_corrupt_one(disc_model: ShapeModel) -> None:
    assert disc_model.patch is not None
    d = patch_to_dict(disc_model.patch)
    back = patch_from_dict(d, disc_model.levels[0].points)
    assert np.array_equal(back.image, disc_model.patch.image) and back.origin == disc_model.patch.origin
    assert np.array_equal(back.mask, disc_model.patch.mask)
    with pytest.raises(TeachError, match="teach the part again"):
        patch_from_dict({"origin_px": [0, 0], "png_base64": "not base64!"}, disc_model.levels[0].points)
    with pytest.raises(TeachError, match="teach the part again"):
        patch_from_dict({"origin_px": [0, 0], "png_base64": "AAAA"}, disc_model.levels[0].points)


def test_jackknife_sees_errors_shared_by_neighbours() -> None:
    """A line fit (y = a + b x) whose residuals are independent: jackknife ~ textbook; with one block
    of points shifted together: the jackknife grows, the textbook hardly."""
    rng = np.random.default_rng(3)
    x = np.linspace(-50, 50, 400)
    pts = np.stack([x, np.zeros_like(x)], axis=1)
    J = np.stack([np.ones_like(x), x / 50.0, (x / 50.0) ** 2 - 1 / 3], axis=1)
    r = rng.normal(0, 0.1, len(x))
    w = np.ones_like(x)
    Cc, Cj = classical(J, r, w, 1.0), jackknife(pts, J, r, w)
    assert 0.3 < Cj[0, 0] / Cc[0, 0] < 3.0
    r2 = r + np.where(x > 25, 0.5, 0.0)  # a quarter of the points pulled together
    Cc2, Cj2 = classical(J, r2 - r2.mean(), w, 1.0), jackknife(pts, J, r2 - r2.mean(), w)
    assert Cj2[1, 1] > 5 * Cc2[1, 1]
    H = honest_cov(pts, J, r2 - r2.mean(), w, 1.0)
    assert H[1, 1] >= Cj2[1, 1] * 0.999


def test_combine_widens_by_disagreement() -> None:
    C = np.diag([0.01, 0.01, 1e-6])
    p, Cm, chi = combine(np.zeros(3), C, np.array([0.01, 0.0, 0.0]), C)
    assert chi < 1 and Cm[0, 0] == pytest.approx(0.005)
    p, Cm, chi = combine(np.zeros(3), C, np.array([1.0, 0.0, 0.0]), C)
    assert chi > 10 and p[0] == pytest.approx(0.5) and Cm[0, 0] == pytest.approx(0.005 * chi)


def test_merge_reports_the_disagreement_it_cannot_explain() -> None:
    """Two fits that agree within their 1-sigma: the merged 1-sigma is theirs combined, nothing added.
    Two that disagree far beyond it (a sharp fit and a loose one 1.4 px apart): the estimate stays where
    the sharper fit leads, and its 1-sigma is of the order of the disagreement (0.4 of it here), not of the
    sharp fit."""
    Ce, Cp = np.diag([0.12 ** 2, 0.12 ** 2, 1e-6]), np.diag([0.55 ** 2, 0.55 ** 2, 4e-6])
    p, C, chi = merge(np.zeros(3), Ce, np.array([0.05, 0.0, 0.0]), Cp)
    _, C0, _ = combine(np.zeros(3), Ce, np.array([0.05, 0.0, 0.0]), Cp)
    assert chi < 1 and np.allclose(C, C0)
    d = np.array([1.366, 0.0, 0.0])
    p, C, chi = merge(np.zeros(3), Ce, d, Cp)
    _, C0, _ = combine(np.zeros(3), Ce, d, Cp)
    assert chi > 1 and 0.0 < p[0] < 0.2  # the sharper fit leads
    assert 0.35 * 1.366 < math.sqrt(C[0, 0]) < 1.366
    assert math.sqrt(C[0, 0]) > 1.5 * math.sqrt(C0[0, 0])  # more than the chi-square widening gave
