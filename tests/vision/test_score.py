"""The match score, the find-time contrast threshold and the model's edge selection, in isolation.

Synthetic edges where the answer is known (a straight step, its shifts, rotations and polarity),
a noise estimate against the noise put in, and the screw-head teach image of the real corpus,
whose model must follow the head's outline rather than the wood grain and the socket's glints.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from bench.pick_cases import load_cases
from vision import shape
from vision.image import gradients
from vision.shape.score import direction_score, find_threshold, noise_sigma
from vision.shape.teaching import _edge_points, coherent_chains


def _step(contrast: float = 60.0, blur: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A vertical step edge at x = 50 (dark left, bright right) and its gradient image (sigma 1)."""
    img = np.full((100, 100), 100.0, np.float32)
    img[:, 50:] += contrast
    img = cv2.GaussianBlur(img, (0, 0), blur)
    gx, gy = gradients(np.clip(img, 0, 255).astype(np.uint8), 1.0)
    return img, cv2.merge([gx, gy])


def _points(x: float, normal_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    ys = np.arange(20.0, 80.0, 2.0)
    q = np.stack([np.full_like(ys, x), ys], axis=1)
    a = math.radians(normal_deg)
    n = np.tile([math.cos(a), math.sin(a)], (len(ys), 1))
    return q, n


def _score(G: np.ndarray, q: np.ndarray, n: np.ndarray, polarity: str = "ignore_local_polarity") -> float:
    return direction_score(G, q, n, np.ones(len(q), bool), 2.0, polarity, 0.5)[0]


@pytest.mark.parametrize("blur", [0.3, 2.5])
def test_points_on_the_edge_score_one_and_a_pixel_off_still_counts(blur: float) -> None:
    _, G = _step(blur=blur)
    assert _score(G, *_points(49.5)) == pytest.approx(1.0, abs=0.02)
    assert _score(G, *_points(48.5)) >= 0.95  # a pixel off: the edge is within the full-weight band
    assert _score(G, *_points(50.5)) >= 0.95
    assert 0.3 <= _score(G, *_points(47.5)) <= 0.8 or blur > 2  # two pixels: counted with less weight
    # three pixels off sees only the flank of the edge (which a blurred edge has wide): no edge there
    assert _score(G, *_points(46.5)) == 0.0
    assert _score(G, *_points(45.0)) == 0.0


def test_direction_must_agree() -> None:
    _, G = _step()
    assert _score(G, *_points(49.5, 20.0)) > 0.2
    assert _score(G, *_points(49.5, 45.0)) == 0.0  # beyond the 30 deg limit
    assert _score(G, *_points(49.5, 90.0)) == 0.0


def test_polarity_rules() -> None:
    _, G = _step()
    q, n = _points(49.5)
    assert _score(G, q, -n, "use_polarity") == 0.0
    assert _score(G, q, -n, "ignore_global_polarity") == pytest.approx(1.0, abs=0.02)
    mixed = n.copy()
    mixed[::2] *= -1  # half the points taught with the other contrast
    assert _score(G, q, mixed, "use_polarity") == pytest.approx(0.5, abs=0.05)
    assert _score(G, q, mixed, "ignore_global_polarity") == pytest.approx(0.5, abs=0.05)
    assert _score(G, q, mixed, "ignore_local_polarity") == pytest.approx(1.0, abs=0.02)


def test_contrast_does_not_matter_above_the_threshold() -> None:
    _, strong = _step(120.0)
    _, weak = _step(15.0)
    q, n = _points(49.5)
    assert _score(weak, q, n) == pytest.approx(_score(strong, q, n), abs=0.02)


def test_score_is_over_the_visible_points() -> None:
    _, G = _step()
    q, n = _points(49.5)
    vis = np.arange(len(q)) < len(q) // 2 + 3
    s, agree, n_vis = direction_score(G, q, n, vis, 2.0, "ignore_local_polarity", 0.5)
    assert s == pytest.approx(1.0, abs=0.02) and n_vis == vis.sum() and agree == n_vis
    # fewer visible than min_visible: no score at all
    assert direction_score(G, q, n, np.arange(len(q)) < 5, 2.0, "ignore_local_polarity", 0.5)[0] == 0.0


@pytest.mark.parametrize("sigma", [1.0, 4.0, 10.0])
def test_noise_estimate(sigma: float) -> None:
    rng = np.random.default_rng(3)
    ramp = np.add.outer(np.linspace(40, 160, 300), np.linspace(0, 50, 400))  # smooth light falloff
    img = np.clip(np.rint(ramp + rng.normal(0, sigma, ramp.shape)), 0, 255).astype(np.uint8)
    assert noise_sigma(img) == pytest.approx(sigma, rel=0.15, abs=0.3)


def test_find_threshold_lowers_only_for_faint_parts_on_clean_images() -> None:
    rng = np.random.default_rng(4)
    clean = np.clip(np.rint(120 + rng.normal(0, 0.7, (200, 200))), 0, 255).astype(np.uint8)
    noisy = np.clip(np.rint(120 + rng.normal(0, 12, (200, 200))), 0, 255).astype(np.uint8)
    taught = 3.0
    assert find_threshold(clean, 1.0, taught, part_grad=40.0) == taught  # good contrast: as taught
    faint = find_threshold(clean, 1.0, taught, part_grad=2.0)
    assert 0.5 <= faint < 1.0  # a quarter of the faint part's edges, above the noise
    assert find_threshold(noisy, 1.0, taught, part_grad=2.0) == taught  # the noise would pass a lower one


def test_coherent_chains_follow_an_outline_not_the_texture() -> None:
    """A faint disc on a textured background: its outline is one chain; the texture's maxima,
    which touch each other everywhere, fall apart into short pieces."""
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.normal(0, 1, (160, 160)).astype(np.float32), (0, 0), 1.2)
    img = 120 + 5 * tex / tex.std()  # grain of 5 grey levels against a step of 25
    yy, xx = np.mgrid[0:160, 0:160]
    img += 25.0 * (np.hypot(xx - 80, yy - 80) < 45)
    img = np.clip(img, 0, 255).astype(np.uint8)
    _, nrm, _, ipx = _edge_points(img, 1.0, 2.0, (0.0, 0.0, 159.0, 159.0))  # the model's edge points
    n, lab = coherent_chains(ipx, nrm)
    r = np.hypot(ipx[:, 0] - 80, ipx[:, 1] - 80)
    on_circle = np.abs(r - 45) <= 1.5
    sizes = np.bincount(lab, minlength=n)
    circle_chain = np.bincount(lab[on_circle]).argmax()
    assert sizes[circle_chain] >= 0.6 * 2 * math.pi * 45  # most of the circumference in one chain
    texture = sizes[np.setdiff1d(np.unique(lab[np.abs(r - 45) > 4]), [circle_chain])]
    assert np.median(texture) < 10 and texture.max() < 0.5 * sizes[circle_chain]
    # a plain 8-connected labelling would join the texture into networks as large as the outline
    mask = np.zeros((160, 160), np.uint8)
    mask[ipx[:, 1], ipx[:, 0]] = 1
    n8, lab8 = cv2.connectedComponents(mask, connectivity=8)
    off = lab8[ipx[:, 1], ipx[:, 0]][np.abs(r - 45) > 4]
    assert np.bincount(off).max() >= 0.5 * sizes[circle_chain]


def test_screw_head_model_follows_the_outline() -> None:
    """The screw heads' teach ROI (wood grain, a specular square socket): the model's level-0
    points lie on the head's round outline (Hough centre (122, 246), radius ~50 px) far more than
    before chains and length priority (21 %), ahead of socket and grain."""
    case = {c.id: c for c in load_cases()}["robertson_screw_heads"]
    m = shape.teach(case.teach_image(), case.roi)
    u, v, w, h = case.roi
    p = m.levels[0].points + np.array([u + w / 2, v + h / 2])
    r = np.hypot(p[:, 0] - 122.0, p[:, 1] - 246.0)
    assert np.mean(np.abs(r - 50.0) < 6.0) >= 0.35


def test_top_level_features_spread_over_a_level0_only_model() -> None:
    """A part small enough that the model has level 0 only (the double cross at 0.35 size, 38
    points): the exhaustive search's features cover the whole part, not its first rows."""
    from bench.pick_cases import scaled

    case = scaled({c.id: c for c in load_cases()}["sick_edgematcher_multi"], 0.35)
    m = shape.teach(case.teach_image(), case.roi)
    assert m.top_level == 0 and len(m.levels[0].points) > len(m.levels[0].features)
    pts = m.levels[0].points
    f = pts[m.levels[0].features]
    extent = pts.max(axis=0) - pts.min(axis=0)
    assert np.all(f.max(axis=0) - f.min(axis=0) >= 0.85 * extent)
    first = pts[: len(f)]  # what taking the first points in storage order gave
    assert not np.all(first.max(axis=0) - first.min(axis=0) >= 0.85 * extent)
