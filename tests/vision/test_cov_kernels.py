"""The compiled covariances (``vision.shape.cov_kernels``) answer what their numpy references in
``vision.shape.uncertainty`` answer: textbook, block jackknife, their merge, and an edge fit's (x, y,
theta) covariance over a similarity and over the plane homography."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vision.shape import cov_kernels as ck
from vision.shape import uncertainty as un


def _line_fit(seed: int, shift: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.linspace(-50, 50, 400)
    y = rng.uniform(-20, 20, len(x))
    pts = np.stack([x, y], axis=1)
    J = np.stack([np.ones_like(x), x / 50.0, y / 20.0, (x / 50.0) ** 2 - 1 / 3], axis=1)
    r = rng.normal(0, 0.1, len(x)) + np.where(x > 25, shift, 0.0)
    w = np.where(rng.random(len(x)) < 0.1, 0.0, rng.uniform(0.3, 1.0, len(x)))
    return pts, J, r - r.mean(), w


@pytest.mark.parametrize("shift", [0.0, 0.5])
def test_honest_cov_as_numpy(shift: float) -> None:
    pts, J, r, w = _line_fit(3, shift)
    M = np.eye(3, 4)
    want = un.honest_cov(pts, J, r, w, 2.0, M)
    got = ck.honest_cov(pts, J, r, w, 2.0, M)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    assert np.array_equal(ck.blocks_of(pts), un.blocks_of(pts))


def test_singular_and_too_few_blocks_are_infinite() -> None:
    H = np.diag([1.0, 1.0, 0.0])
    assert np.all(np.isinf(ck.classical_cov(H, 1.0, 1.0)))
    assert np.all(np.isinf(un.classical_of(H, 1.0, 1.0)))
    Hb = np.zeros((16, 3, 3))
    Hb[:3] = np.eye(3)  # three blocks hold points: a jackknife needs four
    assert np.all(np.isinf(ck.jackknife_cov(Hb.sum(axis=0), np.zeros(3), Hb, np.zeros((16, 3)))))


@pytest.mark.parametrize("perspective", [False, True])
def test_edge_cov_as_numpy(perspective: bool) -> None:
    rng = np.random.default_rng(5)
    t = np.linspace(0, 2 * math.pi, 240, endpoint=False)
    m = np.stack([60 * np.cos(t), 35 * np.sin(t)], axis=1)  # an ellipse's outline, relative to its centre
    nm = np.stack([np.cos(t) / 60, np.sin(t) / 35], axis=1)
    nm /= np.linalg.norm(nm, axis=1, keepdims=True)
    th, sc = math.radians(23.0), 1.02
    R = np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
    q = sc * m @ R.T + np.array([300.5, 200.25])
    n = nm @ R.T
    off = rng.normal(0, 0.08, len(t)) + np.where(t < 0.8, 0.3, 0.0)
    ok = rng.random(len(t)) > 0.05
    want = un.edge_cov(off, ok, m, q, n, th, sc, 3.0, perspective)
    got = ck.edge_cov(off, ok, m, q, n, th, sc, 3.0, perspective)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)


def test_a_homographys_covariance_is_judged_at_its_own_optimum() -> None:
    """An edge fit's homography covariance from residuals taken at a similarity's points (a tilted
    view): the perspective the similarity misses is not noise; the 1-sigma is that of the noise alone."""
    rng = np.random.default_rng(11)
    t = np.linspace(0, 2 * math.pi, 400, endpoint=False)
    rad, drad = 50 + 10 * np.cos(3 * t) + 5 * np.sin(5 * t), -30 * np.sin(3 * t) + 25 * np.cos(5 * t)
    m = np.stack([rad * np.cos(t), rad * np.sin(t)], axis=1)  # a lobed outline (no conic: a homography is fixed)
    tan = np.stack([drad * np.cos(t) - rad * np.sin(t), drad * np.sin(t) + rad * np.cos(t)], axis=1)
    nm = np.stack([tan[:, 1], -tan[:, 0]], axis=1) / np.linalg.norm(tan, axis=1, keepdims=True)
    q = m + np.array([300.0, 200.0])
    ok = np.ones(len(t), bool)
    noise = rng.normal(0, 0.05, len(t))
    J, _, _ = un.edge_system(noise, ok, m, q, nm, 0.0, 1.0, True)
    tilt = J[:, 6:8] @ np.array([2e-5, -1.5e-5])  # a few degrees of tilt: some tenths of a px at the ends
    assert 0.2 < np.abs(tilt).max() < 0.9
    clean = un.edge_cov(noise, ok, m, q, nm, 0.0, 1.0, 1.0, True)
    assert np.all(np.isfinite(clean))
    for cov in (un.edge_cov(noise + tilt, ok, m, q, nm, 0.0, 1.0, 1.0, True),
                ck.edge_cov(noise + tilt, ok, m, q, nm, 0.0, 1.0, 1.0, True)):
        assert math.sqrt(cov[2, 2]) == pytest.approx(math.sqrt(clean[2, 2]), rel=0.2)
        assert math.sqrt(cov[0, 0]) == pytest.approx(math.sqrt(clean[0, 0]), rel=0.2)
