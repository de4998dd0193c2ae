"""Where the arm is in a fixed camera's image: the tool, and the calibration plate it carries.

A fixed camera sees the arm whenever the arm is over what it looks at; a part model taught on, or a
match found on, the arm's image is the arm's (issue 34: a teach right after the hand-eye capture
learned the plate's edge, and the gripper then closed on nothing). With an active **eye-to-hand**
hand-eye (``T_base_cam``, and ``T_tool_target`` for the plate on the tool), the region the arm
covers in the image is the projection, at the robot's current pose, of

- the tool: a disc of :data:`TOOL_RADIUS_MM` around the tool centre, at the tool's height and
  :data:`WRIST_RISE_MM` above it (the gripper, its fingers open, and the wrist);
- the plate it carries: the calibration target's extent (the hand-eye's ``target``, else the
  config's ``calibration.target``) grown by :data:`PLATE_MARGIN_MM`, at ``T_base_tool @ T_tool_target``.

Points behind the camera are left out; the region is the convex hull of the rest (a conservative
outline; the forearm and the upper arm are not modelled). A camera on the arm (eye-in-hand) or a
mapping without the camera's pose (n-point) gives no region: nothing is refused or masked then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g

TOOL_RADIUS_MM = 60.0
"""The gripper's reach around the tool centre (the production run's view margin)."""
WRIST_RISE_MM = 100.0
PLATE_MARGIN_MM = 10.0
MIN_DEPTH_M = 0.05
"""Points nearer the camera than this (or behind it) are left out of the outline."""


@dataclass(frozen=True)
class ArmView:
    """The arm's region in one camera image: a convex outline (image pixels)."""

    hull_px: NDArray[np.float32]
    """The outline's corners, ``(N, 2)`` pixels (may reach beyond the image)."""
    size: tuple[int, int]
    """The image's ``(width, height)``."""
    what: str
    """What the region holds, in words ("the tool", "the tool and the calibration plate it carries")."""

    @property
    def mask(self) -> NDArray[np.bool_]:
        """True where the arm may be, ``(height, width)``."""
        w, h = self.size
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, np.round(self.hull_px).astype(np.int32), 1)
        return mask.astype(bool)

    def share_of(self, roi: tuple[float, float, float, float] | list[float] | None) -> float:
        """The share (0..1) of the rectangle ``roi`` ``[u, v, w, h]`` (None: the whole image) the arm covers."""
        w_img, h_img = self.size
        if roi is None:
            u0, v0, u1, v1 = 0, 0, w_img, h_img
        else:
            u, v, w, h = (float(x) for x in roi)
            u0, v0 = max(0, int(math.floor(u))), max(0, int(math.floor(v)))
            u1, v1 = min(w_img, int(math.ceil(u + w))), min(h_img, int(math.ceil(v + h)))
        if u1 <= u0 or v1 <= v0:
            return 0.0
        return float(self.mask[v0:v1, u0:u1].mean())

    def covers(self, u_px: float, v_px: float) -> bool:
        return cv2.pointPolygonTest(self.hull_px.reshape(-1, 1, 2), (float(u_px), float(v_px)), False) >= 0


def arm_view(mapping: Any, T_base_tool: Any, config: Any = None) -> ArmView | None:
    """The arm's region in the image of ``mapping``'s camera at ``T_base_tool`` (None: not a fixed camera
    with an eye-to-hand hand-eye, or the arm is not in the image)."""
    cam = getattr(mapping, "camera", None)
    calib = getattr(mapping, "calib", None) or {}
    if getattr(mapping, "kind", None) != "handeye" or calib.get("setup") != "eye-to-hand" or cam is None:
        return None
    T_tool = np.asarray(T_base_tool, dtype=np.float64)
    T_cam_base = g.invert(np.asarray(calib["T_base_cam"], dtype=np.float64))
    a = np.linspace(0.0, 2 * math.pi, 24, endpoint=False)
    ring = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)]) * TOOL_RADIUS_MM * 1e-3
    p = T_tool[:3, 3]
    pts = [p + ring, p + ring + [0.0, 0.0, WRIST_RISE_MM * 1e-3]]
    what = "the tool"
    plate = _plate_corners(calib, config)
    if plate is not None and "T_tool_target" in calib:
        T_base_target = T_tool @ np.asarray(calib["T_tool_target"], dtype=np.float64)
        pts.append(g.transform_points(T_base_target, plate))
        what = "the tool and the calibration plate it carries"
    P_cam = g.transform_points(T_cam_base, np.concatenate(pts))
    P_cam = P_cam[P_cam[:, 2] > MIN_DEPTH_M]
    if len(P_cam) < 3:
        return None
    uv = cam.project(P_cam)
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv) < 3:
        return None
    big = 4.0 * max(cam.width, cam.height)  # keep cv2's int32 pixels sane; the hull is clipped by the image
    hull = cv2.convexHull(np.clip(uv, -big, big).astype(np.float32)).reshape(-1, 2)
    lo, hi = hull.min(axis=0), hull.max(axis=0)
    if hi[0] < 0 or hi[1] < 0 or lo[0] > cam.width - 1 or lo[1] > cam.height - 1:
        return None  # the outline lies wholly outside the image
    return ArmView(hull, (int(cam.width), int(cam.height)), what)


def _plate_corners(calib: dict[str, Any], config: Any) -> NDArray[np.float64] | None:
    """The carried target's outline corners in its own frame (metres), grown by the margin; None: unknown."""
    from calibration.targets import TargetError, target_from_dict

    if "T_tool_target" not in calib:
        return None
    targets = getattr(config, "targets", None) or {}
    name = calib.get("target") or getattr(getattr(config, "calibration", None), "target", None)
    desc = targets.get(name) if isinstance(name, str) else None
    if desc is None:
        r = 0.1  # a plate of unknown size: 10 cm around its origin
        return np.array([[x, y, 0.0] for x in (-r, r) for y in (-r, r)])
    try:
        target = target_from_dict(desc, f"targets.{name}")
    except (TargetError, ValueError):
        return None
    extent = getattr(target, "extent_m", None)  # a 3D target has none: its points' box instead
    if extent is not None:
        x0, y0, x1, y1 = extent()
    else:
        xyz = target.points().xyz_m
        x0, y0, x1, y1 = float(xyz[:, 0].min()), float(xyz[:, 1].min()), float(xyz[:, 0].max()), float(xyz[:, 1].max())
    m = PLATE_MARGIN_MM * 1e-3
    return np.array([[x, y, 0.0] for x in (x0 - m, x1 + m) for y in (y0 - m, y1 + m)])


def arm_view_now(services: Any, camera_id: str, robot_id: str | None = None) -> ArmView | None:
    """The arm's region in ``camera_id``'s image at the robot's current pose, through the active calibration
    (None: no fixed-camera hand-eye is active, or the robot's pose cannot be read now)."""
    from cellctl.mapping import NoCalibration, active_mapping
    from drivers.base import DriverError

    rid = robot_id or services.config.calibration.robot
    if rid not in services.cell.robots:
        return None
    try:
        mapping = active_mapping(services, camera_id, rid, "handeye", True)
        state = services.cell.robot(rid).ensure_open().state()
    except (NoCalibration, DriverError):
        return None
    return arm_view(mapping, state.T_base_tool, services.config)
