"""Image points to metric points on a plane (HALCON's ``image_points_to_world_plane``).

Each pixel is unprojected through the full lens model to a ray and intersected with the plane
``z = 0`` of the frame given by ``T_cam_plane`` (e.g. a calibration target's ``T_cam_target``).
Results are in the plane's frame, metres.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel
from calibration.geometry import as_transform


class PlaneError(CalibrationError):
    """A pixel's ray misses the plane (parallel, or the plane lies behind the camera)."""


def image_to_plane(camera: CameraModel, T_cam_plane: ArrayLike, uv_px: ArrayLike) -> NDArray[np.float64]:
    """(N, 2) pixels to (N, 3) points in the plane frame (metres, z = 0).

    Raises PlaneError naming the first pixel whose ray does not meet the plane in front of the camera.
    """
    T = as_transform(T_cam_plane, "T_cam_plane")
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    rays = camera.unproject(uv)
    R, t = T[:3, :3], T[:3, 3]
    n = R[:, 2]
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(n @ t) / denom
    bad = ~np.isfinite(lam) | (lam <= 0) | ~np.all(np.isfinite(rays), axis=1)
    if np.any(bad):
        k = int(np.nonzero(bad)[0][0])
        raise PlaneError(f"pixel ({uv[k, 0]:g}, {uv[k, 1]:g}): its ray does not meet the plane in front of "
                         "the camera")
    P_cam = rays * lam[:, None]
    P = (P_cam - t) @ R
    P[:, 2] = 0.0
    return np.asarray(P, dtype=np.float64)


def plane_to_image(camera: CameraModel, T_cam_plane: ArrayLike, xy_m: ArrayLike) -> NDArray[np.float64]:
    """(N, 2) plane points (metres) to (N, 2) pixels (the inverse of ``image_to_plane``)."""
    T = as_transform(T_cam_plane, "T_cam_plane")
    xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    P = np.column_stack([xy, np.zeros(len(xy))])
    return camera.project(P @ T[:3, :3].T + T[:3, 3])
