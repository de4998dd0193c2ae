"""Synthetic views and detections (tests, benchmarks, and a capture plan for operators)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3, make_transform
from calibration.intrinsics import IntrinsicsError
from calibration.observations import Detection
from calibration.targets import Target

F64 = NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# synthetic data (tests, benchmarks, and a capture plan for operators)


def plan_views(camera: CameraModel, target: Target, n_views: int, rng: np.random.Generator,
               fill: float = 0.5, max_tilt_deg: float = 40.0, margin_px: float = 3.0,
               whole_outline: bool = False) -> list[F64]:
    """``T_cam_target`` poses of a varied capture: the target tilted up to ``max_tilt_deg`` about
    both axes, placed so that it covers about ``fill`` of the image width, moved around so that
    the set covers the image corners. Every pose keeps all target points ``margin_px`` inside
    the image — or, with ``whole_outline``, the target's whole printed outline (``extent_m``: a
    circle plate's frame must be seen to be detected)."""
    xyz = target.points().xyz_m
    x0, y0 = xyz[:, :2].min(axis=0)
    x1, y1 = xyz[:, :2].max(axis=0)
    if whole_outline and hasattr(target, "extent_m"):
        x0, y0, x1, y1 = target.extent_m()
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]])
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    size_m = max(x1 - x0, y1 - y0)
    dist = camera.fx * size_m / (fill * camera.width)
    poses: list[F64] = []
    spots = [(0.0, 0.0), (-1, -1), (1, -1), (-1, 1), (1, 1), (0, -1), (0, 1), (-1, 0), (1, 0)]
    attempts = 0
    while len(poses) < n_views and attempts < 200 * n_views:
        attempts += 1
        k = len(poses)
        sx, sy = spots[k % len(spots)]
        tilt = np.radians(max_tilt_deg) * rng.uniform(-1, 1, 2)
        if k % 3 == 0:
            tilt[0] = np.radians(max_tilt_deg) * rng.choice([-1, 1]) * rng.uniform(0.5, 1)
        elif k % 3 == 1:
            tilt[1] = np.radians(max_tilt_deg) * rng.choice([-1, 1]) * rng.uniform(0.5, 1)
        spin = rng.uniform(-0.3, 0.3)
        Rm = exp_so3(np.array([[tilt[0], 0, 0]]))[0] @ exp_so3(np.array([[0, tilt[1], 0]]))[0] \
            @ exp_so3(np.array([[0, 0, spin]]))[0]
        d = dist * rng.uniform(0.85, 1.15)
        reach = 0.95
        for _ in range(15):
            q = np.array([[camera.cx + sx * reach * camera.width / 2,
                           camera.cy + sy * reach * camera.height / 2]])
            ray = camera.unproject(q)[0]
            t = ray / np.linalg.norm(ray) * d - Rm @ centre
            uv = camera.project(corners @ Rm.T + t)
            if np.all(np.isfinite(uv)) and np.all(uv >= margin_px) \
                    and np.all(uv[:, 0] <= camera.width - 1 - margin_px) \
                    and np.all(uv[:, 1] <= camera.height - 1 - margin_px):
                poses.append(make_transform(Rm, t))
                break
            reach *= 0.93
    if len(poses) < n_views:
        raise IntrinsicsError("could not plan the requested views: the target does not fit the image")
    return poses


def synthetic_detections(camera: CameraModel, target: Target, poses: Sequence[F64], noise_px: float,
                         rng: np.random.Generator) -> list[Detection]:
    """Project the target's points with ``camera`` and add Gaussian pixel noise (tests, benchmarks)."""
    tp = target.points()
    out = []
    for k, T in enumerate(poses):
        uv = camera.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + rng.normal(0.0, noise_px, (len(tp.ids), 2))
        out.append(Detection(image=f"view{k:02d}", found=True, ids=tp.ids.copy(), uv=uv,
                             image_size=camera.size))
    return out
