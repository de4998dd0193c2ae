"""Closed-form AX = XB solutions: OpenCV's five and our pair-filtered least squares, with pair statistics."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.geometry import (
    invert,
    log_so3,
    make_transform,
    rotation_angle,
)
from calibration.handeye.frames import (
    hand_pose,
)
from calibration.handeye.model import (
    OPENCV_METHODS,
    Mat4,
)


# --------------------------------------------------------------------------------------------
# closed forms and AX = XB statistics
# --------------------------------------------------------------------------------------------
def relative_motions(H: Sequence[Mat4], C: Sequence[Mat4]) -> list[tuple[int, int, Mat4, Mat4, float]]:
    out = []
    for i in range(len(H)):
        for j in range(i + 1, len(H)):
            A = invert(H[j]) @ H[i]
            B = C[j] @ invert(C[i])
            out.append((i, j, A, B, float(np.degrees(rotation_angle(A[:3, :3])))))
    return out


def solve_pairs(pairs: Sequence[tuple[int, int, Mat4, Mat4, float]]) -> Mat4:
    """Least-squares AX = XB over the given pairs: rotation by Kabsch on the rotation vectors
    (``log R_A = R_X log R_B``), translation by linear least squares."""
    a = np.array([log_so3(A[:3, :3]) for _, _, A, _, _ in pairs])
    b = np.array([log_so3(B[:3, :3]) for _, _, _, B, _ in pairs])
    U, _, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    M = np.vstack([A[:3, :3] - np.eye(3) for _, _, A, _, _ in pairs])
    y = np.concatenate([R @ B[:3, 3] - A[:3, 3] for _, _, A, B, _ in pairs])
    t = np.linalg.lstsq(M, y, rcond=None)[0]
    return make_transform(R, t)


def axxb_residuals(pairs: Sequence[tuple[int, int, Mat4, Mat4, float]], X: Mat4) -> tuple[NDArray[np.float64],
                                                                                           NDArray[np.float64]]:
    """Per pair: rotation (deg) and translation (mm) of ``inv(A X) · X B``."""
    rot, tr = [], []
    Xi = invert(X)
    for _, _, A, B, _ in pairs:
        E = Xi @ invert(A) @ X @ B
        rot.append(np.degrees(rotation_angle(E[:3, :3])))
        tr.append(1e3 * np.linalg.norm((A @ X)[:3, 3] - (X @ B)[:3, 3]))
    return np.array(rot), np.array(tr)


def stats(x: NDArray[np.float64]) -> dict[str, float]:
    if x.size == 0:
        return {"mean": float("nan"), "rms": float("nan"), "max": float("nan")}
    return {"mean": float(np.mean(x)), "rms": float(np.sqrt(np.mean(x * x))), "max": float(np.max(x))}


def opencv_handeye(setup: str, G: Sequence[Mat4], C: Sequence[Mat4], method: str) -> Mat4:
    """One of OpenCV's closed forms; eye-to-hand passes ``inv(G)`` as OpenCV documents."""
    H = [hand_pose(setup, g) for g in G]
    R, t = cv2.calibrateHandEye([h[:3, :3] for h in H], [h[:3, 3] for h in H],
                                [c[:3, :3] for c in C], [c[:3, 3] for c in C], method=OPENCV_METHODS[method])
    return make_transform(np.asarray(R), np.asarray(t).ravel())
