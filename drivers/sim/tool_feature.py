"""The tool's feature drawn over a sim camera's frame: a bright disk in a dark ring on the tool.

The renderer (``drivers.sim.imaging.renderer``) knows planes fixed to the base or the tool flange as
targets; a feature on the gripper, seen by a fixed camera, is drawn here instead, as an overlay
on the finished frame: each circle (the ring, then the disk) is sampled in 3-D in the tool's
x/y plane at the scene's ``tool_feature.offset_mm`` from the true flange pose, projected through
the full camera model (lens distortion included), and filled with its area coverage per pixel
(an 8 x 8 sub-pixel grid), softened by the scene's ``blur_sigma_px`` and given the scene's
Gaussian noise. So the disk's image centroid is where the camera model puts the disk (to a few
thousandths of a pixel for a disk facing the camera), and the feature's truth is exact.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from drivers.sim.scene import ImagingSpec, ToolFeatureSpec

SUBPIXELS: Final = 8
"""Sub-pixel samples per axis for the coverage of an edge pixel."""
RIM_SAMPLES: Final = 180
_SHIFT: Final = 8  # fixed-point fraction bits for cv2.fillPoly


def T_base_feature(T_base_tool: NDArray[np.float64], spec: ToolFeatureSpec) -> NDArray[np.float64]:
    """Pose of the feature's disk (its centre; z along the tool axis) in the base frame."""
    T = np.asarray(T_base_tool, dtype=np.float64)
    return np.asarray(T @ g.make_transform(np.eye(3), np.asarray(spec.offset_mm, dtype=np.float64) * 1e-3),
                      dtype=np.float64)


def rim_px(camera: CameraModel, T_cam_feature: NDArray[np.float64], diameter_mm: float) -> NDArray[np.float64]:
    """(RIM_SAMPLES, 2) pixels of a circle of ``diameter_mm`` in the feature's x/y plane; NaN behind the camera."""
    a = np.linspace(0.0, 2 * np.pi, RIM_SAMPLES, endpoint=False)
    r_m = 0.5 * diameter_mm * 1e-3
    pts = np.column_stack([r_m * np.cos(a), r_m * np.sin(a), np.zeros_like(a)])
    return camera.project(pts @ T_cam_feature[:3, :3].T + T_cam_feature[:3, 3])


def _coverage(poly_px: NDArray[np.float64], x0: int, y0: int, w: int, h: int) -> NDArray[np.float64]:
    """Fraction of each pixel of the window ``(x0, y0, w, h)`` inside the polygon."""
    s = SUBPIXELS
    mask = np.zeros((h * s, w * s), dtype=np.uint8)
    # pixel (i, j) spans [i - 0.5, i + 0.5]; sub-pixel a of it has its centre at x0 - 0.5 + (a + 0.5) / s
    sub = (poly_px - [x0, y0] + 0.5) * s - 0.5
    pts = np.round(sub * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return np.asarray(mask.reshape(h, s, w, s).mean(axis=(1, 3)), dtype=np.float64)


def draw_tool_feature(pixels: NDArray[np.uint8], camera: CameraModel, T_cam_tool: NDArray[np.float64],
                      spec: ToolFeatureSpec, imaging: ImagingSpec, rng: np.random.Generator) -> NDArray[np.uint8]:
    """``pixels`` with the feature drawn where the camera sees it (a copy; unchanged when out of view)."""
    T_cam_feature = T_base_feature(T_cam_tool, spec)
    circles = [(d, grey) for d, grey in ((spec.ring_diameter_mm, spec.ring_grey_dn), (spec.diameter_mm, spec.grey_dn))
               if d > 0]
    rims = [rim_px(camera, T_cam_feature, d) for d, _ in circles]
    outer = rims[0]
    if not np.all(np.isfinite(outer)):
        return pixels  # behind the camera
    h_img, w_img = pixels.shape[:2]
    pad = int(np.ceil(3 * imaging.blur_sigma_px)) + 2
    x0 = max(int(np.floor(outer[:, 0].min())) - pad, 0)
    y0 = max(int(np.floor(outer[:, 1].min())) - pad, 0)
    x1 = min(int(np.ceil(outer[:, 0].max())) + pad + 1, w_img)
    y1 = min(int(np.ceil(outer[:, 1].max())) + pad + 1, h_img)
    if x1 <= x0 or y1 <= y0:
        return pixels  # out of view
    out = pixels.copy()
    win = out[y0:y1, x0:x1].astype(np.float64)
    covered = np.zeros_like(win)
    for rim, (_, grey) in zip(rims, circles, strict=True):
        cov = _coverage(rim, x0, y0, x1 - x0, y1 - y0)
        if imaging.blur_sigma_px > 0:
            cov = cv2.GaussianBlur(cov, (0, 0), imaging.blur_sigma_px)
        win = cov * grey + (1.0 - cov) * win
        covered = np.maximum(covered, cov)
    if imaging.noise_sigma > 0:
        win += covered * rng.normal(0.0, imaging.noise_sigma, win.shape)
    out[y0:y1, x0:x1] = np.clip(np.round(win), 0, 255).astype(np.uint8)
    return out
