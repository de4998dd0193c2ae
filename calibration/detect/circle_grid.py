"""OpenCV circle grids (symmetric and asymmetric) through ``cv2.findCirclesGrid``.

Ids are ``row * cols + col`` of ``calibration.targets.CircleGrid``. A symmetric grid looks the
same after a half turn (and a square one after a quarter turn): we pick the order that is
right-handed on screen with the x axis pointing rightwards (angle in (-90°, 90°]), a fixed
convention. An asymmetric grid with an odd number of rows is unambiguous; we keep OpenCV's order
after checking its handedness.

``Detection.uv_ellipse`` holds OpenCV's blob centres; ``uv`` the same corrected for perspective
bias with the bias model of ``calibration.detect.circle_plate``. A centre that its grid
neighbours do not predict (OpenCV occasionally misplaces one) is left out.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.chessboard import canonical_order
from calibration.detect.mark_grid import consistent_marks, perspective_bias
from calibration.detect.precision import gradient_sigma_px
from calibration.observations import Detection
from calibration.targets import CircleGrid


def blob_detector(image_area_px: int, n_circles: int) -> cv2.SimpleBlobDetector:
    """A blob detector for dark circles from a few pixels up to a grid filling the image."""
    p = cv2.SimpleBlobDetector.Params()
    p.filterByColor = True
    p.blobColor = 0
    p.minArea = 10
    p.maxArea = max(100.0, image_area_px / max(n_circles, 1))
    p.filterByInertia = True
    p.minInertiaRatio = 0.2
    p.filterByConvexity = True
    p.minConvexity = 0.85
    return cv2.SimpleBlobDetector.create(p)


def find_circles_opencv(grey: NDArray[np.uint8], target: CircleGrid) -> NDArray[np.float64] | None:
    """(rows*cols, 2) centres in OpenCV's order, or None."""
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if target.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    h, w = grey.shape
    ok, centres = cv2.findCirclesGrid(grey, (target.cols, target.rows), flags=flags,
                                      blobDetector=blob_detector(h * w, target.cols * target.rows))
    if not ok or centres is None:
        return None
    return np.asarray(centres, dtype=np.float64).reshape(-1, 2)


def circles_beyond_border(grey: NDArray[np.uint8], G: NDArray[np.float64], asymmetric: bool) -> int:
    """Blobs one grid step beyond the found grid's border: > 0 means a larger grid (OpenCV then
    happily returns a sub-grid of it, with ids that belong to no printed target)."""
    if asymmetric:
        if len(G) < 3:
            return 0
        outer = [G[1] + (G[0] - G[2]), G[-2] + (G[-1] - G[-3])]
    else:
        outer = [G[0] + (G[0] - G[1]), G[-1] + (G[-1] - G[-2])]
    outer += [G[:, 0] + (G[:, 0] - G[:, 1]), G[:, -1] + (G[:, -1] - G[:, -2])]
    pts = np.concatenate(outer)
    h, w = grey.shape
    keypoints = blob_detector(h * w, G.shape[0] * G.shape[1]).detect(grey)
    if not keypoints:
        return 0
    kp = np.array([k.pt for k in keypoints], dtype=np.float64)
    size = np.array([k.size for k in keypoints], dtype=np.float64)
    step = float(np.median(np.hypot(*np.diff(G, axis=1).reshape(-1, 2).T)))
    # The grid's own blobs give the size a printed circle has here; noise, vignetting and
    # compression make smaller or larger dark specks beyond the border that are no circles.
    dg = np.hypot(G.reshape(-1, 2)[:, None, 0] - kp[None, :, 0], G.reshape(-1, 2)[:, None, 1] - kp[None, :, 1])
    own = size[np.argmin(dg, axis=1)[dg.min(axis=1) < 0.25 * step]]
    d = np.hypot(pts[:, None, 0] - kp[None, :, 0], pts[:, None, 1] - kp[None, :, 1])
    near = d.min(axis=1) < 0.25 * step
    if own.size:
        ratio = size[np.argmin(d, axis=1)] / float(np.median(own))
        near &= (ratio > 0.7) & (ratio < 1.4)
    return int(near.sum())


def detect_circle_grid(grey: NDArray[np.uint8], target: CircleGrid, image_name: str = "") -> Detection:
    """Circle centres of ``target`` in ``grey`` with target ids, or a reason why not."""
    kind = "asymmetric" if target.asymmetric else "symmetric"
    uv = find_circles_opencv(grey, target)
    if uv is None:
        return Detection(image_name, False, reason=f"no {kind} {target.cols}x{target.rows} circle grid found "
                         "(grid not fully visible, blurred, or a different size)")
    cols, rows = target.cols, target.rows
    G = uv.reshape(rows, cols, 2)
    extra = circles_beyond_border(grey, G, target.asymmetric)
    if extra:
        return Detection(image_name, False, reason=f"the circle grid is larger than the target's {cols}x{rows} "
                         f"({extra} circles beyond its border); check cols/rows in the target file")
    if target.asymmetric:
        ex = G[0, -1] - G[0, 0]
        ey = G[-1, 0] - G[0, 0]
        if ex[0] * ey[1] - ex[1] * ey[0] < 0:
            G = G[::-1, ::-1]
    else:
        G = canonical_order(grey, G, cols, rows, colour_cue=False)
    raw = np.ascontiguousarray(G.reshape(-1, 2))
    pts = target.points()
    grid = pts.xyz_m[:, :2] / target.pitch_m
    # OpenCV now and then places one blob centre off (a merged or split blob): drop centres that
    # their neighbours do not predict (the plate detector's leave-one-out check)
    keep = consistent_marks(grid, raw)
    ids, raw, grid = pts.ids[keep], raw[keep], grid[keep]
    corrected = raw - perspective_bias(grid, raw, target.diameter_mm / 2 / target.pitch_mm)
    radius_px = 0.5 * target.diameter_mm / target.pitch_mm * float(np.median(np.hypot(*np.diff(G, axis=1)
                                                                                       .reshape(-1, 2).T)))
    sigma = gradient_sigma_px(grey, raw, window_sigma_px=max(radius_px, 1.5))
    return Detection(image_name, True, ids=ids.copy(), uv=corrected, uv_ellipse=raw, uv_sigma_px=sigma)
