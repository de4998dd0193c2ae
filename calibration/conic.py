"""Perspective bias of circular marks: the imaged circle's centre is not the image of its centre.

A circle of radius ``r`` in the target plane maps through the plane-to-image homography to a
conic whose centre differs from the projected circle centre (Heikkilä, IEEE PAMI 2000). This
module computes that difference for a known camera and pose, so that a solver can correct the
fitted ellipse centres inside its loop. Lens distortion is applied to both centres, which is
exact to first order over a mark's small extent.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.camera_model import CameraModel


def conic_centres_normalized(T_cam_target: ArrayLike, centres_m: ArrayLike, radius_m: float
                             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ideal normalized image coordinates of (conic centre, projected circle centre) per mark."""
    T = np.asarray(T_cam_target, dtype=np.float64)
    H = np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
    Hinv = np.linalg.inv(H)
    P = np.asarray(centres_m, dtype=np.float64).reshape(-1, 3)
    conic_c = np.empty((len(P), 2))
    for k, (cx, cy, _) in enumerate(P):
        Ct = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [-cx, -cy, cx * cx + cy * cy - radius_m**2]])
        Ci = Hinv.T @ Ct @ Hinv
        conic_c[k] = -np.linalg.solve(Ci[:2, :2], Ci[:2, 2])
    proj = (H @ np.column_stack([P[:, :2], np.ones(len(P))]).T).T
    return conic_c, proj[:, :2] / proj[:, 2:3]


def circle_centre_bias_px(camera: CameraModel, T_cam_target: ArrayLike, centres_m: ArrayLike,
                          radius_m: float) -> NDArray[np.float64]:
    """(N, 2) pixels: imaged-ellipse centre minus the image of the circle centre.

    Subtract it from a fitted ellipse centre to get the image of the mark's centre.
    """
    conic_c, proj_c = conic_centres_normalized(T_cam_target, centres_m, radius_m)
    a = camera.normalized_to_pixels(camera.distort(conic_c))
    b = camera.normalized_to_pixels(camera.distort(proj_c))
    return np.asarray(a - b, dtype=np.float64)
