"""Small compiled helpers (numba) the matcher's kernels share: a dense solve and inverse, a median and
a k-th smallest value, written out so that their first compile is cheap.

numba's ``np.linalg.solve``/``inv`` (LAPACK behind shape checks, copies and an exception path),
``np.median`` and ``np.sort`` each cost seconds of compile time per signature on a fresh cache (the
matcher's first start); these loops cost a fraction of that and run as fast on the 3x3-10x10 systems
and the few hundred values the fits use. ``solve`` is Gaussian elimination with partial pivoting (the
algorithm of LAPACK's ``gesv``, so the same answers to rounding) and, like it, calls a matrix singular
only on an exactly zero pivot; it answers ``ok=False`` instead of raising.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
_Fn = TypeVar("_Fn", bound=Callable[..., Any])


def compiled(**options: Any) -> Callable[[_Fn], _Fn]:
    """numba's ``njit`` as the matcher's kernels use it: cached on disk (``cache=True``), and without
    the C-callable wrapper numba otherwise builds beside every compiled function so that it can be
    passed around as a first-class function value (none of these is): about 4% of the kernels'
    compile on a fresh cache, nothing at run time. ``options``: njit's others (``inline``,
    ``boundscheck``).

    In these kernels numba compiles its ``np.empty``/``np.zeros``/``np.full`` once per (shape, dtype
    argument) pair: 2-d float arrays name ``np.float64`` (what ``np.full`` passes on), so the 2-d
    allocations share one; no ``np.ones``, and booleans and integers by ``np.empty`` set in loops."""
    jit: Any = njit  # numba's type stubs do not list no_cfunc_wrapper (numba takes it)
    return cast(Callable[[_Fn], _Fn], jit(cache=True, no_cfunc_wrapper=True, **options))


@compiled()
def bilinear(img: NDArray[np.float32], x: float, y: float) -> float:
    """``vision.image.bilinear`` of ``img`` at one place (pixel centres at integers, clamped at the border):
    one compiled sampler that the profile and patch kernels call (LLVM inlines it where they are linked;
    numba's own ``inline="always"`` copied it into each caller's typing and lowering)."""
    h, w = img.shape
    x = min(max(x, 0.0), w - 1.001)
    y = min(max(y, 0.0), h - 1.001)
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] + (img[y0, x0 + 1] - img[y0, x0]) * fx
    bot = img[y0 + 1, x0] + (img[y0 + 1, x0 + 1] - img[y0 + 1, x0]) * fx
    return top + (bot - top) * fy


@compiled()
def lu_factor(A: F64) -> tuple[F64, NDArray[np.int64], bool]:
    """``A`` (k, k) factored in place of a copy as ``P A = L U`` (unit ``L`` below the diagonal, ``U``
    on and above it), the pivot row of each step, and whether every pivot is non-zero."""
    k = A.shape[0]
    LU = A.copy()
    piv = np.empty(k, np.int64)
    ok = True
    for c in range(k):
        p = c
        best = abs(LU[c, c])
        for r in range(c + 1, k):
            v = abs(LU[r, c])
            if v > best:
                best, p = v, r
        piv[c] = p
        if p != c:
            for j in range(k):
                LU[c, j], LU[p, j] = LU[p, j], LU[c, j]
        d = LU[c, c]
        if d == 0.0 or not np.isfinite(d):
            ok = False
            continue
        for r in range(c + 1, k):
            f = LU[r, c] / d
            LU[r, c] = f
            if f != 0.0:
                for j in range(c + 1, k):
                    LU[r, j] -= f * LU[c, j]
    return LU, piv, ok


@compiled()
def lu_solve(LU: F64, piv: NDArray[np.int64], b: F64) -> F64:
    """``x`` with ``A x = b`` from ``lu_factor``'s ``LU``, ``piv`` (``b`` (k,) is not changed)."""
    k = LU.shape[0]
    x = b.copy()
    for c in range(k):
        p = piv[c]
        if p != c:
            x[c], x[p] = x[p], x[c]
    for r in range(k):
        s = x[r]
        for j in range(r):
            s -= LU[r, j] * x[j]
        x[r] = s
    for r in range(k - 1, -1, -1):
        s = x[r]
        for j in range(r + 1, k):
            s -= LU[r, j] * x[j]
        x[r] = s / LU[r, r]
    return x


@compiled(inline="always")  # a thin wrapper: no library of its own
def solve(A: F64, b: F64) -> tuple[F64, bool]:
    """``x`` with ``A x = b`` (``A`` (k, k), ``b`` (k,), both unchanged) and ``ok``: False (``x``
    undefined) where a pivot is exactly zero, where ``np.linalg.solve`` raises."""
    LU, piv, ok = lu_factor(A)
    if not ok:
        return np.zeros(A.shape[0]), False
    return lu_solve(LU, piv, b), True


@compiled(inline="always")  # a thin wrapper: no library of its own
def inv(A: F64) -> tuple[F64, bool]:
    """``A^-1`` (k, k) and ``ok`` as ``solve``'s."""
    k = A.shape[0]
    LU, piv, ok = lu_factor(A)
    out = np.zeros((k, k), np.float64)
    if not ok:
        return out, False
    e = np.zeros(k)
    for c in range(k):
        for r in range(k):
            e[r] = 1.0 if r == c else 0.0
        col = lu_solve(LU, piv, e)
        for r in range(k):
            out[r, c] = col[r]
    return out, True


@compiled()
def kth_smallest(a: F64, kth: int) -> float:
    """The ``kth`` smallest (0-based) of ``a`` (not changed): ``np.sort(a)[kth]`` by selection."""
    w = a.copy()
    lo, hi = 0, w.shape[0] - 1
    while hi > lo:
        mid = (lo + hi) // 2  # median of three as the pivot
        if w[mid] < w[lo]:
            w[mid], w[lo] = w[lo], w[mid]
        if w[hi] < w[lo]:
            w[hi], w[lo] = w[lo], w[hi]
        if w[hi] < w[mid]:
            w[hi], w[mid] = w[mid], w[hi]
        pv = w[mid]
        i, j = lo, hi
        while i <= j:
            while w[i] < pv:
                i += 1
            while w[j] > pv:
                j -= 1
            if i <= j:
                w[i], w[j] = w[j], w[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            break
    return w[kth]


@compiled()
def next_above(a: F64, kth: int, v: float) -> float:
    """``np.sort(a)[kth + 1]`` given ``v = np.sort(a)[kth]``: the smallest value ranked after it
    (``v`` itself when it repeats there)."""
    below_or_eq = 0
    nxt = np.inf
    for x in a:
        if x <= v:
            below_or_eq += 1
        elif x < nxt:
            nxt = x
    return v if below_or_eq > kth + 1 else nxt


@compiled()
def median(a: F64) -> float:
    """``np.median(a)`` of ``a`` (n,) (n >= 1) by selection: the middle value, or the mean of the two."""
    n = a.shape[0]
    h = (n - 1) // 2
    v = kth_smallest(a, h)
    if n % 2 == 1:
        return v
    return (v + next_above(a, h, v)) / 2.0
