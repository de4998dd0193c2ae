"""Compiled Schur-complement solve of the bundle solver's normal equations (numba).

The bundle problem's normal equations have an arrow structure: the intrinsics couple to every view,
each view's pose (left rotation increment ``w``, then translation) only to its own observations.
``schur_reduce`` eliminates the poses view by view from the Marquardt-damped per-view blocks that
``kernels.normal_blocks`` accumulates (``A_v``, ``B_v``, ``D_v`` and the gradients, in weighted pixels),
leaving the intrinsics' reduced system; once its step ``dc`` is solved, ``back_substitute`` gives
each pose's step. Plain loops (a 6 x 6 Gauss-Jordan inverse per view), not numba's ``np.linalg``,
for a cheap first compile. Cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@njit(cache=True)
def schur_reduce(A: F64, B: F64, D: F64, gc: F64, gv: F64, lam: float) -> tuple[F64, F64, F64, F64, int]:
    """The Marquardt-damped arrow-structured normal equations with the poses eliminated view by view
    (Schur complement): ``S = A' - sum_k B_k D_k'^-1 B_kᵀ``, ``rhs = -gc + sum_k B_k D_k'^-1 gv_k`` and
    the damped ``D_k'^-1`` (``X' = X + lam diag(X)``), and a status: 0 done, 1 not finite, 2 a ``D_k'``
    is singular. ``S`` and ``rhs`` come scaled by ``sc = sqrt(diag S)`` (``S / sc scᵀ``, ``rhs / sc``;
    the solution is then divided by ``sc``), with ``sc`` itself. C-contiguous float64 arrays (one
    compiled signature).

    Plain loops and a 6 x 6 Gauss-Jordan inverse (partial pivoting), not numba's ``np.linalg``: its
    LAPACK bindings made this step the dearest compile of the solver (20 s of CPU on a cold cache)."""
    nv = D.shape[0]
    nc = A.shape[0]
    S = np.empty((nc, nc))
    rhs = np.empty(nc)
    Dinv = np.empty((nv, 6, 6))
    sc = np.ones(nc)
    for x in (A.ravel(), B.ravel(), D.ravel()):
        for v in x:
            if not np.isfinite(v):
                return S, rhs, Dinv, sc, 1
    for i in range(nc):
        rhs[i] = -gc[i]
        for j in range(nc):
            S[i, j] = A[i, j]
        S[i, i] += lam * A[i, i]
    M = np.empty((6, 12))
    BD = np.empty((nc, 6))
    for k in range(nv):
        for i in range(6):
            for j in range(6):
                M[i, j] = D[k, i, j]
                M[i, 6 + j] = 1.0 if i == j else 0.0
            M[i, i] += lam * D[k, i, i]
        for c in range(6):
            p = c
            for r in range(c + 1, 6):
                if abs(M[r, c]) > abs(M[p, c]):
                    p = r
            if M[p, c] == 0.0:
                return S, rhs, Dinv, sc, 2
            if p != c:
                for j in range(12):
                    M[c, j], M[p, j] = M[p, j], M[c, j]
            piv = M[c, c]
            for j in range(12):
                M[c, j] /= piv
            for r in range(6):
                f = M[r, c]
                if r != c and f != 0.0:
                    for j in range(12):
                        M[r, j] -= f * M[c, j]
        for i in range(6):
            for j in range(6):
                Dinv[k, i, j] = M[i, 6 + j]
        for i in range(nc):
            acc = 0.0
            for j in range(6):
                s = 0.0
                for m in range(6):
                    s += B[k, i, m] * Dinv[k, m, j]
                BD[i, j] = s
                acc += s * gv[k, j]
            rhs[i] += acc
        for i in range(nc):
            for j in range(nc):
                s = 0.0
                for m in range(6):
                    s += BD[i, m] * B[k, j, m]
                S[i, j] -= s
    # the scaled system: a parameter without information (zero column, or a negative round-off) keeps
    # scale 1: dividing by its ~0 diagonal overflowed to inf (a 6-view ChArUco set, rational model)
    big = 0.0
    for p in range(nc):
        big = max(big, abs(S[p, p]))
    for p in range(nc):
        if np.isfinite(S[p, p]) and S[p, p] > 1e-300 + 1e-15 * big:
            sc[p] = np.sqrt(S[p, p])
    for i in range(nc):
        rhs[i] /= sc[i]
        if not np.isfinite(rhs[i]):
            return S, rhs, Dinv, sc, 1
        for j in range(nc):
            S[i, j] /= sc[i] * sc[j]
            if not np.isfinite(S[i, j]):
                return S, rhs, Dinv, sc, 1
    return S, rhs, Dinv, sc, 0


@njit(cache=True)
def back_substitute(Dinv: F64, B: F64, gv: F64, dc: F64) -> F64:
    """The poses' step ``dv_k = D_k'^-1 (-gv_k - B_kᵀ dc)`` (V, 6) once the intrinsics' ``dc`` is known."""
    nv, nc = B.shape[0], B.shape[1]
    dv = np.empty((nv, 6))
    u = np.empty(6)
    for k in range(nv):
        for m in range(6):
            s = -gv[k, m]
            for i in range(nc):
                s -= B[k, i, m] * dc[i]
            u[m] = s
        for j in range(6):
            s = 0.0
            for m in range(6):
                s += Dinv[k, j, m] * u[m]
            dv[k, j] = s
    return dv
