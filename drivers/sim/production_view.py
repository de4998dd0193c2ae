"""What the camera sees of a production scene's parts, and their truth with image boxes.

Each part is a plane of its own at its true pose (``PlanarObject``): lying on the table, carried
by the tool (tilted with it), or put down in the place area. The renderer
(``drivers.sim.imaging.renderer``) sorts the planes by depth, so a carried part hides what lies below it.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from drivers.sim.imaging import PlanarObject
from drivers.sim.production import ProductionParts


def _reflectance(outline_mm: list[list[float]], holes_mm: list[list[list[float]]], value: float,
                 x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """The part in its own frame (metres): ``value`` inside the outline and outside the holes, NaN elsewhere."""
    from drivers.sim.world import part_mask

    inside = part_mask(outline_mm, holes_mm, 0.0, 0.0, 0.0, x, y)
    out = np.full(x.shape, np.nan)
    out[inside] = value
    return out


def production_objects(parts: ProductionParts, T_cam_base: NDArray[np.float64],
                       T_base_tool_true: NDArray[np.float64]) -> list[PlanarObject]:
    """The parts as planes in the camera frame, each bounded by its outline's box."""
    spec = parts.spec.part
    shade = functools.partial(_reflectance, spec.outline_mm, spec.holes_mm, spec.reflectance)
    poly = np.asarray(spec.outline_mm, dtype=np.float64) * 1e-3
    box = (float(poly[:, 0].min()), float(poly[:, 1].min()), float(poly[:, 0].max()), float(poly[:, 1].max()))
    return [PlanarObject(T_cam_base @ T, shade, box) for _, T in parts.poses(T_base_tool_true)]


def roi_px(parts: ProductionParts, camera: CameraModel, T_cam_base: NDArray[np.float64],
           T_base_part: NDArray[np.float64]) -> list[float] | None:
    """The part's bounding box ``[u, v, w, h]`` in the image (clipped to it), None when not in view."""
    pts = g.transform_points(T_cam_base, parts.outline_in_base(T_base_part))
    uv = camera.project(pts)
    if not np.all(np.isfinite(uv)):
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    lo = np.maximum(lo, [-0.5, -0.5])
    hi = np.minimum(hi, [camera.width - 0.5, camera.height - 0.5])
    if np.any(hi <= lo):
        return None
    return [float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])]


def production_truth(parts: ProductionParts, camera: CameraModel, T_base_cam: NDArray[np.float64],
                     T_base_tool_true: NDArray[np.float64]) -> dict[str, Any]:
    """``{"parts": [{"id", "state", "T_base_part", "roi_px"}], "place_grid": {...}, ...}`` (metres, px)."""
    T_cam_base = g.invert(T_base_cam)
    spec = parts.spec
    out_parts = [{"id": p.id, "state": p.state, "T_base_part": T.tolist(),
                  "roi_px": roi_px(parts, camera, T_cam_base, T)} for p, T in parts.poses(T_base_tool_true)]
    held = parts.held()
    return {
        "parts": out_parts,
        "place_grid": {"kind": "grid", **spec.place_grid.model_dump(mode="json")},
        "pick_area": spec.pick_area.model_dump(mode="json"),
        "place_area": spec.place_area.model_dump(mode="json"),
        "part": spec.part.model_dump(mode="json"),
        "gripper": {"closed": parts.closed, "holding": None if held is None else held.id,
                    "width_mm": parts.width_mm()},
    }
