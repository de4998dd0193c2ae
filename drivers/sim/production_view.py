"""What the camera sees of a production scene's parts, and their truth with image boxes.

Each part is a plane of its own at its true pose (``PlanarObject``): lying on the table, carried
by the tool (tilted with it), or put down in the place area. The renderer
(``drivers.sim.imaging.renderer``) sorts the planes by depth, so a carried part hides what lies below it.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from drivers.sim.imaging import PlanarObject
from drivers.sim.production import ProductionParts
from drivers.sim.scene import SceneError


def _reflectance(outline_mm: list[list[float]], holes_mm: list[list[list[float]]], value: float,
                 x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """The part in its own frame (metres): ``value`` inside the outline and outside the holes, NaN elsewhere."""
    from drivers.sim.outline import part_mask

    inside = part_mask(outline_mm, holes_mm, 0.0, 0.0, 0.0, x, y)
    out = np.full(x.shape, np.nan)
    out[inside] = value
    return out


class _Lying:
    """Every lying part on one plane (its frame: the base's, shifted to the parts' top face).

    Each ray is tested exactly (``part_mask``) against the parts whose outline, grown by
    ``GROW_MM``, covers its cell of a coarse label raster (two labels a cell: parts may touch), so
    a ray meets one or two parts' tests instead of every part's.
    """

    CELL_MM = 0.5
    GROW_MM = 1.5

    def __init__(self, outline_mm: list[list[float]], holes_mm: list[list[list[float]]], value: float,
                 poses_mm: list[tuple[float, float, float]], extent_m: tuple[float, float, float, float]) -> None:
        import cv2

        self.outline, self.holes, self.value, self.poses = outline_mm, holes_mm, value, poses_mm
        self.x0, self.y0 = extent_m[0] * 1e3, extent_m[1] * 1e3
        w = int(math.ceil((extent_m[2] - extent_m[0]) * 1e3 / self.CELL_MM)) + 1
        h = int(math.ceil((extent_m[3] - extent_m[1]) * 1e3 / self.CELL_MM)) + 1
        self.labels = np.zeros((2, h, w), np.int16)
        poly = np.asarray(outline_mm, dtype=np.float64)
        grow = max(1, int(math.ceil(2 * self.GROW_MM / self.CELL_MM)))
        for k, (x_mm, y_mm, angle_deg) in enumerate(poses_mm):
            a = math.radians(angle_deg)
            R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            pts = (poly @ R.T + [x_mm, y_mm] - [self.x0, self.y0]) / self.CELL_MM
            mask = np.zeros((h, w), np.uint8)
            cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], 1)
            cv2.polylines(mask, [np.round(pts).astype(np.int32)], True, 1, grow)
            on = mask.astype(bool)
            first = on & (self.labels[0] == 0)
            self.labels[0][first] = k + 1
            self.labels[1][on & ~first] = k + 1

    def __call__(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        from drivers.sim.outline import part_mask

        out = np.full(x.shape, np.nan)
        _, h, w = self.labels.shape
        ix = np.clip(((x * 1e3 - self.x0) / self.CELL_MM).astype(np.int64), 0, w - 1)
        iy = np.clip(((y * 1e3 - self.y0) / self.CELL_MM).astype(np.int64), 0, h - 1)
        for layer in self.labels:
            lab = layer[iy, ix]
            hit = np.flatnonzero(lab)
            if hit.size == 0:
                continue
            order = hit[np.argsort(lab[hit], kind="stable")]
            ks, starts = np.unique(lab[order], return_index=True)
            for k, lo, hi in zip(ks, starts, [*starts[1:], len(order)], strict=True):
                sel = order[lo:hi]
                x_mm, y_mm, angle_deg = self.poses[int(k) - 1]
                inside = part_mask(self.outline, self.holes, x_mm, y_mm, angle_deg, x[sel], y[sel])
                out[sel[inside]] = self.value
        return out


def production_objects(parts: ProductionParts, T_cam_base: NDArray[np.float64],
                       T_base_tool_true: NDArray[np.float64], s_m: float | None = None) -> list[PlanarObject]:
    """The parts as planes in the camera frame.

    The parts that lie on the table share one plane at their top face (bounded by the box around
    them all: one plane for the renderer, not one per part); a held part is a plane of its own at
    its pose, bounded by its outline's box.
    """
    spec = parts.spec.part
    poly = np.asarray(spec.outline_mm, dtype=np.float64) * 1e-3
    box = (float(poly[:, 0].min()), float(poly[:, 1].min()), float(poly[:, 0].max()), float(poly[:, 1].max()))
    objs = []
    lying: list[tuple[float, float, float]] = []
    for part, T in parts.poses(T_base_tool_true, s_m):
        if part.state == "fallen":
            continue
        if part.state == "held":
            shade = functools.partial(_reflectance, spec.outline_mm, spec.holes_mm, spec.reflectance)
            objs.append(PlanarObject(T_cam_base @ T, shade, box))
        else:
            lying.append((float(T[0, 3]) * 1e3, float(T[1, 3]) * 1e3, math.degrees(math.atan2(T[1, 0], T[0, 0]))))
    if lying:
        r_m = parts.spec.part_radius_mm() * 1e-3
        xy = np.array([p[:2] for p in lying]) * 1e-3
        extent = (float(xy[:, 0].min()) - r_m, float(xy[:, 1].min()) - r_m,
                  float(xy[:, 0].max()) + r_m, float(xy[:, 1].max()) + r_m)
        T_base_top = g.make_transform(np.eye(3), [0.0, 0.0, parts.top_z_mm * 1e-3])
        lying_shade = _Lying(spec.outline_mm, spec.holes_mm, spec.reflectance, lying, extent)
        objs.append(PlanarObject(T_cam_base @ T_base_top, lying_shade, extent))
    fixture = parts.spec.fixture
    if fixture is not None:  # the nest plate: a plane at its top face, the table seen through its pockets
        outline = [list(p) for p in fixture.outline_mm]
        holes = [[list(p) for p in h] for h in fixture.holes_mm]
        fpoly = np.asarray(outline, dtype=np.float64) * 1e-3
        fbox = (float(fpoly[:, 0].min()), float(fpoly[:, 1].min()), float(fpoly[:, 0].max()),
                float(fpoly[:, 1].max()))
        shade = functools.partial(_reflectance, outline, holes, fixture.reflectance)
        objs.append(PlanarObject(T_cam_base @ np.array(fixture.T_base_fixture(parts.table_z_m)), shade, fbox))
    return objs


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
        **({} if spec.fixture is None else {"fixture": fixture_truth(parts, camera, T_cam_base)}),
        "gripper": {"closed": parts.closed, "holding": None if held is None else held.id,
                    "width_mm": parts.width_mm(), "closes_on_part": parts.closes_on_part,
                    "faults": parts.faults},
    }


def fixture_truth(parts: ProductionParts, camera: CameraModel, T_cam_base: NDArray[np.float64]) -> dict[str, Any]:
    """The nest plate's true frame (on its top face), its image box, and each pocket's slot: where a
    placed part's pose (its reference point on its top face) is when it lies centred in the pocket."""
    fixture = parts.spec.fixture
    if fixture is None:
        raise SceneError("this production scene has no fixture (nest plate): its slots have no truth")
    T_fix = np.array(fixture.T_base_fixture(parts.table_z_m))
    pts = np.array([[x * 1e-3, y * 1e-3, 0.0] for x, y in fixture.outline_mm])
    uv = camera.project(g.transform_points(T_cam_base @ T_fix, pts))
    roi = None
    if np.all(np.isfinite(uv)):
        lo, hi = np.maximum(uv.min(axis=0), -0.5), np.minimum(uv.max(axis=0), [camera.width - 0.5, camera.height - 0.5])
        roi = None if np.any(hi <= lo) else [float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])]
    slots = []
    for x, y in fixture.slots_mm:
        T = T_fix @ g.make_transform(np.eye(3), [x * 1e-3, y * 1e-3, 0.0])
        T[2, 3] = parts.top_z_mm * 1e-3  # a part in the pocket lies on the table
        slots.append(T.tolist())
    return {"T_base_fixture": T_fix.tolist(), "roi_px": roi, "slots": slots}
