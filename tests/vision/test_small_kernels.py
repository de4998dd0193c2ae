"""The written-out solve, inverse, median and k-th value (``vision.shape.small_kernels``) answer what
numpy answers, and call a singular system what ``np.linalg`` calls singular."""

from __future__ import annotations

import numpy as np
import pytest

from vision.shape import small_kernels as sk


@pytest.mark.parametrize("k", [3, 4, 8, 10])
def test_solve_and_inverse_as_numpy(k: int) -> None:
    rng = np.random.default_rng(k)
    J = rng.normal(size=(50, k)) * np.logspace(0, 3, k)  # normal equations of badly scaled columns
    A = J.T @ J
    b = rng.normal(size=k)
    x, ok = sk.solve(A, b)
    assert ok
    np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-9)
    Ai, ok = sk.inv(A)
    assert ok
    np.testing.assert_allclose(Ai, np.linalg.inv(A), rtol=1e-9, atol=1e-15 * np.abs(np.linalg.inv(A)).max())
    G = rng.normal(size=(k, k))  # not symmetric: the pivoting matters
    np.testing.assert_allclose(sk.solve(G, b)[0], np.linalg.solve(G, b), rtol=1e-9)


def test_singular_is_not_ok() -> None:
    for A in (np.diag([1.0, 1.0, 0.0]), np.zeros((4, 4)), np.ones((3, 3))):
        with pytest.raises(np.linalg.LinAlgError):
            np.linalg.solve(A, np.ones(len(A)))
        assert not sk.solve(A, np.ones(len(A)))[1]
        assert not sk.inv(A)[1]


def test_median_and_kth_as_numpy() -> None:
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 7, 100, 301):
        for a in (rng.normal(size=n), rng.integers(0, 4, n).astype(np.float64)):  # ties
            assert sk.median(a) == np.median(a)
            s = np.sort(a)
            for kth in {0, n // 2, n - 1}:
                assert sk.kth_smallest(a, kth) == s[kth]
                if kth + 1 < n:
                    assert sk.next_above(a, kth, s[kth]) == s[kth + 1]
    a = rng.normal(size=9)
    b = a.copy()
    sk.median(a)
    assert np.array_equal(a, b)  # the input is not reordered
