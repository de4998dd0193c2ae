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
    cx, cy = P[:, 0], P[:, 1]
    n = len(P)
    # the circle (x - cx)^2 + (y - cy)^2 = r^2 as a conic matrix per mark, mapped by H^-1
    Ct = np.zeros((n, 3, 3))
    Ct[:, 0, 0] = Ct[:, 1, 1] = 1.0
    Ct[:, 0, 2] = Ct[:, 2, 0] = -cx
    Ct[:, 1, 2] = Ct[:, 2, 1] = -cy
    Ct[:, 2, 2] = cx * cx + cy * cy - radius_m**2
    Ci = np.einsum("ji,njk,kl->nil", Hinv, Ct, Hinv)
    a, b, d = Ci[:, 0, 0], Ci[:, 0, 1], Ci[:, 1, 1]
    det = a * d - b * b
    e, f = Ci[:, 0, 2], Ci[:, 1, 2]
    conic_c = -np.column_stack([(d * e - b * f) / det, (a * f - b * e) / det])
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
