"""Where a cell's fiducials are (base frame) and where they are seen in a frame (``drift.fiducials``).

Marks are found near where the active calibration puts them (``calibration.drift.find_marks``); a
fixed target is detected as any target (``calibration.detect``) and its points put in the base
frame through ``T_base_target_ur``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.drift.fiducials import find_marks, predict_px
from calibration.targets import target_from_dict
from cellctl.config import ConfigError
from cellctl.drift.config import DriftConfig

F64 = NDArray[np.float64]


def fiducial_points(cfg: DriftConfig, targets: dict[str, dict[str, Any]]) -> F64:
    """Every fiducial's position in the base frame: (N, 3) metres."""
    f = cfg.fiducials
    if f.marks_mm is not None:
        return np.asarray(f.marks_mm, dtype=np.float64) * 1e-3
    if f.target is None or f.T_base_target_ur is None:  # the config's validator refuses this already
        raise ConfigError("drift.fiducials needs marks_mm, or target with T_base_target_ur")
    target = target_from_dict(targets[f.target], f"targets.{f.target}")
    pts = target.points()
    return g.transform_points(g.ur_pose_to_transform(list(f.T_base_target_ur)), pts.xyz_m)


def observe(cfg: DriftConfig, targets: dict[str, dict[str, Any]], pixels: NDArray[Any], camera: CameraModel,
            T_base_cam: F64) -> tuple[F64, F64]:
    """(points_base_m (N, 3), uv_px (N, 2) with NaN rows for the fiducials not seen) in ``pixels``."""
    X = fiducial_points(cfg, targets)
    f = cfg.fiducials
    if f.marks_mm is not None:
        pred = predict_px(camera, T_base_cam, X)
        distance_m = np.linalg.norm(X - np.asarray(T_base_cam)[:3, 3], axis=1)
        radius_px = float(np.median(f.mark_diameter_mm * 1e-3 / 2 / distance_m)) * float(camera.K[0, 0])
        return X, find_marks(pixels, pred, cfg.window_px, radius_px)
    target = target_from_dict(targets[str(f.target)], f"targets.{f.target}")
    det = detect(pixels, target, "drift check")
    uv = np.full((len(X), 2), np.nan)
    if det.found:
        index = {int(i): k for k, i in enumerate(target.points().ids)}
        for i, p in zip(det.ids, det.uv, strict=True):
            k = index.get(int(i))
            if k is not None:
                uv[k] = p
    return X, uv
