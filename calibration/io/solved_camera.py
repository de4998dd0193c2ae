"""The camera a hand-eye calibration was solved with, and whether another camera is the same one.

A hand-eye solution ``X`` fits the pixels *through* the intrinsics it was solved with; when the
joint refinement also refined the intrinsics (``intrinsics_refined``), ``he.json["camera"]`` is that
refined camera and only it reproduces the fit. Mapping a pixel through another camera (the camera
file the hand-eye started from, or a newer intrinsics calibration) moves the mapped point by as
much as the intrinsics differ (1 % in fx is ~3 px at the image edge, millimetres on the plane).
So every mapping takes the hand-eye's own camera, and another camera is accepted only when it
maps every pixel of the image to the same ray within :data:`SAME_CAMERA_TOLERANCE_PX`.

Pure functions on the JSON of ``he.json`` / ``cam.json`` (calibration/io).
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from calibration.camera_model import CameraModel
from calibration.io.camera_file import CameraFileError, camera_from_json

SAME_CAMERA_TOLERANCE_PX: Final = 0.05
"""Two camera models are the same camera when, over a grid of the image, the ray one model gives a
pixel projects through the other within this distance (px). A refinement of the intrinsics that
matters for mapping moves pixels by tenths of a pixel or more; a rounding of the file's numbers by
far less."""

_GRID = 9  # pixels per image side checked (the corners and edges included: distortion is largest there)


def handeye_camera(calib: dict[str, Any], source: str = "the hand-eye calibration") -> CameraModel | None:
    """The camera ``calib`` (he.json) was solved with (``calib["camera"]``), or None when the file
    carries none (made by an older version, or elsewhere). Raises CameraFileError when it is malformed."""
    cam = calib.get("camera")
    if cam is None:
        return None
    return camera_from_json(cam, f"{source}: camera")


def camera_difference_px(a: CameraModel, b: CameraModel) -> float:
    """Largest image distance (px) between where ``a`` and ``b`` put the same ray, over a 9x9 grid of
    ``a``'s image (rays of ``a``'s pixels projected through ``b``); inf when the sizes differ or a ray
    leaves ``b``'s model."""
    if tuple(a.size) != tuple(b.size):
        return float("inf")
    w, h = a.size
    u, v = np.meshgrid(np.linspace(0.0, w - 1.0, _GRID), np.linspace(0.0, h - 1.0, _GRID))
    uv = np.column_stack([u.ravel(), v.ravel()])
    rays = a.unproject(uv)
    d = np.linalg.norm(b.project(rays) - uv, axis=1)
    if not np.all(np.isfinite(d)):
        return float("inf")
    return float(d.max())


def camera_mismatch(own: CameraModel, other: CameraModel, other_name: str,
                    tolerance_px: float = SAME_CAMERA_TOLERANCE_PX) -> str | None:
    """Why ``other`` is not the camera ``own`` (the hand-eye's), in one line; None when it is the same
    within ``tolerance_px``."""
    if tuple(own.size) != tuple(other.size):
        return (f"{other_name} is {other.width}x{other.height} px, the camera the hand-eye was solved with is "
                f"{own.width}x{own.height} px")
    d = camera_difference_px(own, other)
    if d <= tolerance_px:
        return None
    return (f"{other_name} maps pixels up to {d:.2f} px away from the camera the hand-eye was solved with "
            f"(fx {other.fx:.2f} vs {own.fx:.2f}, fy {other.fy:.2f} vs {own.fy:.2f}, cx {other.cx:.2f} vs "
            f"{own.cx:.2f}, cy {other.cy:.2f} vs {own.cy:.2f}; tolerance {tolerance_px:g} px)")


def handeye_start_camera(calib: dict[str, Any]) -> CameraModel | None:
    """The camera the hand-eye *started* from: ``camera_initial`` when the intrinsics were refined
    jointly, else its own camera (unchanged by the solve); None when the file says neither."""
    start = calib.get("camera_initial")
    if start is not None:
        try:
            return camera_from_json(start, "camera_initial")
        except CameraFileError:
            return None
    if calib.get("intrinsics_refined") is True:
        return None
    try:
        return handeye_camera(calib)
    except CameraFileError:
        return None
