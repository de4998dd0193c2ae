"""Virtual jog-to-mark data with truth: a camera looking down at the robot's table (tests and benches).

The N-point fit it feeds is ``calibration.npoint``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel

F64 = NDArray[np.float64]


def simulate_npoint(rng: np.random.Generator, camera: CameraModel, *, tilt_deg: float = 1.5, height_m: float = 0.5,
                    n_side: int = 3, field_mm: tuple[float, float] = (200.0, 140.0), pixel_sigma_px: float = 0.1,
                    jog_sigma_mm: float = 0.02) -> tuple[F64, F64, Callable[[F64], F64]]:
    """Virtual jog-to-mark data: a camera ``height_m`` above the robot's table (z = 0 of the base),
    looking down, tilted by ``tilt_deg`` about a random horizontal axis, so that image y runs
    against robot y (the usual reflection). Marks on an ``n_side`` x ``n_side`` grid over
    ``field_mm``. Returns (noisy pixels, noisy jogged robot mm, the true pixel→mm map)."""
    from calibration.geometry import invert, make_transform, rotvec_to_matrix, transform_points

    a = rng.uniform(0, 2 * np.pi)
    tilt = rotvec_to_matrix(np.radians(tilt_deg) * np.array([np.cos(a), np.sin(a), 0.0]))
    yaw = rotvec_to_matrix([0.0, 0.0, rng.uniform(-0.3, 0.3)])
    # camera x along base x, camera y along -base y, camera z down: a reflection of the XY plane.
    R_base_cam = yaw @ tilt @ np.diag([1.0, -1.0, -1.0])
    centre = np.array([0.45, 0.05, 0.0])
    T_base_cam = make_transform(R_base_cam, centre - R_base_cam @ np.array([0.0, 0.0, height_m]))
    T_cam_base = invert(T_base_cam)
    gx = np.linspace(-field_mm[0] / 2, field_mm[0] / 2, n_side) * 1e-3
    gy = np.linspace(-field_mm[1] / 2, field_mm[1] / 2, n_side) * 1e-3
    P = np.array([[centre[0] + x, centre[1] + y, 0.0] for y in gy for x in gx])
    uv = camera.project(transform_points(T_cam_base, P)) + rng.normal(0, pixel_sigma_px, (len(P), 2))
    xy = P[:, :2] * 1e3 + rng.normal(0, jog_sigma_mm, (len(P), 2))

    def truth(uv_px: F64) -> F64:
        rays = camera.unproject(uv_px)
        d = rays @ R_base_cam.T
        o = T_base_cam[:3, 3]
        s = -o[2] / d[:, 2]
        return np.asarray((o[None, :2] + s[:, None] * d[:, :2]) * 1e3, dtype=np.float64)

    return uv, xy, truth
