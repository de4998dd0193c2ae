"""Measure fixed fiducials in one frame against a calibration, and re-solve the camera from them.

A fiducial is a point that does not move, with its position in the robot base frame known (a mark
on the table, or a point of a target fixed to it). A fixed camera's calibration (``T_base_cam``
and its intrinsics) says where each fiducial must appear; where it does appear tells how far the
camera has moved since:

- ``drift_px``: RMS over the fiducials of (seen - predicted) in pixels;
- ``drift_mm``: RMS over the fiducials of the distance between where the calibration maps the seen
  pixel (the ray cut with the fiducial's own plane ``z``) and the fiducial's known position: the
  error the cell would make picking there, in millimetres;
- ``drift_deg``: the turn between the calibrated camera pose and the pose the fiducials give
  (PnP through the calibrated intrinsics; 4 or more fiducials), else the in-plane turn of the
  mapped points (3 fiducials);
- ``sigma_mm`` / ``sigma_deg``: the measurement's own uncertainty: the RMS of the mapped points'
  residuals about their best rigid 2D fit divided by sqrt(n - 3) (what the marks' scatter says
  about one check), and the PnP pose's rotation sigma.

Bright marks are found with :func:`find_marks` (a grey-weighted centroid in a window around each
predicted pixel); a target's points come from ``calibration.detect``. Pixels ``(u, v)``, the
centre of the top-left pixel is (0, 0); metres inside, mm and degrees in the names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.pose import PoseEstimationError, estimate_pose

F64 = NDArray[np.float64]
MIN_CONTRAST_DN = 25.0
"""A mark must stand this many grey levels above its window's background."""


class FiducialError(CalibrationError):
    """Too few fiducials were seen for a measurement (the message says how many and which)."""


@dataclass
class Measurement:
    """One drift check's numbers (see the module's docstring)."""

    drift_px: float
    drift_mm: float
    drift_deg: float
    sigma_mm: float
    sigma_deg: float | None
    seen: int
    """Fiducials found and used."""
    residuals_mm: F64
    """(n, 2) mapped - known, base frame x/y, mm, per fiducial used."""

    def as_dict(self) -> dict[str, Any]:
        return {"drift_px": self.drift_px, "drift_mm": self.drift_mm, "drift_deg": self.drift_deg,
                "sigma_mm": self.sigma_mm, "sigma_deg": self.sigma_deg, "seen": self.seen}


def predict_px(camera: CameraModel, T_base_cam: F64, points_base_m: F64) -> F64:
    """Where ``points_base_m`` (N, 3) appear through ``camera`` at ``T_base_cam``: (N, 2) pixels."""
    pts_cam = g.transform_points(g.invert(np.asarray(T_base_cam, dtype=np.float64)),
                                 np.asarray(points_base_m, dtype=np.float64).reshape(-1, 3))
    return np.asarray(camera.project(pts_cam), dtype=np.float64)


def map_to_planes(camera: CameraModel, T_base_cam: F64, uv_px: F64, z_m: F64) -> F64:
    """The rays of ``uv_px`` (N, 2) cut with the planes ``z = z_m`` (N,) of the base frame: (N, 3) metres."""
    xy = camera.undistort_normalized(camera.pixels_to_normalized(np.asarray(uv_px, dtype=np.float64)))
    rays = np.column_stack([xy, np.ones(len(xy))]) @ np.asarray(T_base_cam)[:3, :3].T
    origin = np.asarray(T_base_cam)[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.asarray(z_m, dtype=np.float64) - origin[2]) / rays[:, 2]
    return origin + rays * t[:, None]


def find_marks(image: NDArray[Any], predicted_px: F64, window_px: float, radius_px: float | None = None) -> F64:
    """Each bright mark's centre near its predicted pixel: (N, 2), NaN where none is found.

    In a square window of half-size ``window_px`` around each prediction: the background is the
    window's median; the mark is the bright region (above half-way between background and peak)
    holding the peak, not touching the window's edge (else it is something larger: a part, the
    arm), with an area within 0.3x-3x of a disc of ``radius_px`` when given; its centre is the
    grey-weighted centroid, each pixel weighted by its coverage ``(grey - bg) / (level - bg)``
    clipped to [0, 1], over the region grown by 2 pixels.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    grey = grey.astype(np.float64)
    h, w = grey.shape
    out = np.full((len(predicted_px), 2), np.nan)
    r = int(math.ceil(window_px))
    for k, (u, v) in enumerate(np.asarray(predicted_px, dtype=np.float64)):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        u0, v0 = int(round(u)) - r, int(round(v)) - r
        u1, v1 = u0 + 2 * r + 1, v0 + 2 * r + 1
        if u0 < 0 or v0 < 0 or u1 > w or v1 > h:
            continue
        crop = grey[v0:v1, u0:u1]
        bg = float(np.median(crop))
        smooth = cv2.GaussianBlur(crop, (0, 0), 1.0)
        peak = float(smooth.max())
        if peak - bg < MIN_CONTRAST_DN:
            continue
        mask = (smooth > (bg + peak) / 2).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        pv, pu = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
        lab = int(labels[pv, pu])
        if lab == 0:
            continue
        x, y, bw, bh, area = (int(s) for s in stats[lab])
        if x == 0 or y == 0 or x + bw >= crop.shape[1] or y + bh >= crop.shape[0]:
            continue
        if radius_px is not None and not (0.3 <= area / (math.pi * radius_px**2 + 1e-9) <= 3.0):
            continue
        region = (labels == lab).astype(np.uint8)
        inner = cv2.erode(region, np.ones((3, 3), np.uint8))
        level = float(np.median(crop[inner > 0])) if inner.any() else peak
        if level - bg < MIN_CONTRAST_DN:
            continue
        grown = cv2.dilate(region, np.ones((5, 5), np.uint8)) > 0
        wgt = np.clip((crop - bg) / (level - bg), 0.0, 1.0) * grown
        total = float(wgt.sum())
        if total <= 0:
            continue
        vv, uu = np.mgrid[0:crop.shape[0], 0:crop.shape[1]]
        out[k] = [u0 + float((wgt * uu).sum()) / total, v0 + float((wgt * vv).sum()) / total]
    return out


def _rigid_2d(a: F64, b: F64) -> tuple[F64, F64, float]:
    """The rotation (2x2), translation and angle (rad) that best map points ``a`` onto ``b`` (N, 2)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    H = (a - ca).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, d]) @ U.T
    return R, cb - R @ ca, math.atan2(R[1, 0], R[0, 0])


def measure(camera: CameraModel, T_base_cam: F64, uv_px: F64, points_base_m: F64) -> Measurement:
    """The drift of a fixed camera at ``T_base_cam`` from fiducials ``points_base_m`` (N, 3, metres) seen
    at ``uv_px`` (N, 2; NaN rows: not seen and left out). Needs 3 seen."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_base_m, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(uv), axis=1)
    n = int(ok.sum())
    if n < 3:
        raise FiducialError(f"{n} of {len(X)} fiducials seen; a drift check needs 3 (is one hidden, or has the "
                            "camera moved so far that they left their search windows?)")
    uv, X = uv[ok], X[ok]
    pred = predict_px(camera, T_base_cam, X)
    drift_px = float(np.sqrt(np.mean(np.sum((uv - pred) ** 2, axis=1))))
    mapped = map_to_planes(camera, T_base_cam, uv, X[:, 2])
    d_mm = (mapped[:, :2] - X[:, :2]) * 1e3
    drift_mm = float(np.sqrt(np.mean(np.sum(d_mm**2, axis=1))))
    R, t, angle = _rigid_2d(X[:, :2] * 1e3, mapped[:, :2] * 1e3)
    resid = mapped[:, :2] * 1e3 - ((X[:, :2] * 1e3) @ R.T + t)
    dof = max(n - 3, 1)
    sigma_mm = float(np.sqrt(np.sum(resid**2) / (2 * dof)))
    drift_deg, sigma_deg = abs(math.degrees(angle)), None
    if n >= 4:
        try:
            pose = estimate_pose(camera, X, uv)
            T_base_cam_seen = g.invert(pose.T_cam_target)
            rot, _ = g.transform_error(T_base_cam_seen, np.asarray(T_base_cam, dtype=np.float64))
            drift_deg, sigma_deg = math.degrees(rot), pose.sigma_rot_deg
        except PoseEstimationError:
            pass
    return Measurement(drift_px, drift_mm, drift_deg, sigma_mm, sigma_deg, n, d_mm)


@dataclass
class Resolved:
    """The camera's pose re-solved from the fiducials (intrinsics kept)."""

    T_base_cam: F64
    rms_px: float
    sigma_trans_mm: float
    sigma_rot_deg: float
    shift_mm: float
    """How far the camera's origin moved from the calibration's, mm."""
    shift_deg: float
    """How far the camera turned from the calibration's, degrees."""
    seen: int


def resolve(camera: CameraModel, T_base_cam_old: F64, uv_px: F64, points_base_m: F64) -> Resolved:
    """``T_base_cam`` from fiducials ``points_base_m`` (N, 3) seen at ``uv_px`` (NaN rows left out) through
    ``camera`` (its intrinsics kept); needs 4 seen, not all on one line."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_base_m, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(uv), axis=1)
    if int(ok.sum()) < 4:
        raise FiducialError(f"{int(ok.sum())} of {len(X)} fiducials seen; re-solving the camera's pose needs 4")
    try:
        pose = estimate_pose(camera, X[ok], uv[ok])
    except PoseEstimationError as exc:
        raise FiducialError(f"the camera's pose cannot be solved from the fiducials: {exc}") from exc
    T_new = g.invert(pose.T_cam_target)
    rot, trans = g.transform_error(T_new, np.asarray(T_base_cam_old, dtype=np.float64))
    return Resolved(T_new, pose.rms_px, pose.sigma_trans_mm, pose.sigma_rot_deg, trans * 1e3, math.degrees(rot),
                    int(ok.sum()))
