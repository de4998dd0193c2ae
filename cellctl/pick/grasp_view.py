"""The recipe's grasp seen in the image: where a parallel gripper's fingers stand, which way they close,
how far they open, and what part material lies between them.

A match ``(u, v, angle)`` (or the teach pose: the model's reference point at angle 0) and the recipe's
grasp (``grasp_offset_mm``, ``grasp_yaw_deg``, ``tool_rotvec_rad``) give the gripper centre and its
closing axis in the base frame (``cellctl.pick.pose.grasp``: the fingers close along the tool's y axis,
as a Robotiq 2F's do); the active calibration's local Jacobian at the part (mm per pixel on the working
plane) brings them back into image pixels. The fingers open to ``gripper.open_width_mm`` (the device's
``stroke_mm`` when absent).

``check_material`` walks the closing line across the model's edge points at that pose: the outermost
edges the fingers meet are where they touch the part, their distance the width they would close on. A
line that crosses no edge closes on nothing; a width above the stroke cannot be gripped; a width far
from the recipe's ``grip_width_mm`` fails the device's grip check every cycle (a part taught turned
from its bounding box: the taught x axis, and so the grasp, is not the part's).

Pixels: image coordinates (u right, v down; angles counter-clockwise on screen); lengths mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.mapping import ActiveMapping, NoCalibration, active_mapping
from cellctl.pick.model import PartModel
from cellctl.pick.pose import PartPose, grasp, part_pose
from cellctl.pick.recipe import PickError, Recipe
from cellctl.services import Services

__all__ = ["DEFAULT_STROKE_MM", "GraspImage", "check_material", "grasp_in_image", "taught_grasps"]

DEFAULT_STROKE_MM = 85.0
"""The fingers' full opening when the recipe names no device (a Robotiq 2F-85's)."""
PROBE_PX = 10.0
"""Pixel step of the mapping's local Jacobian."""


@dataclass(frozen=True)
class GraspImage:
    """One grasp drawn in image pixels (a match's or the teach pose's)."""

    centre_px: tuple[float, float]
    """The gripper centre (the grasp point) in the image."""
    axis_px: tuple[float, float]
    """Unit direction (image pixels) the fingers close along."""
    mm_per_px: float
    """Millimetres on the working plane per image pixel along the closing axis."""
    open_mm: float
    """How far the fingers open before the approach, mm."""
    approach_mm: float
    grip_width_mm: float | None
    contacts_px: tuple[tuple[float, float], tuple[float, float]] | None = None
    """Where the fingers meet the part's outermost edges (``check_material``); None: unchecked or nothing."""
    material_mm: float | None = None
    """The part's width between the fingers, mm (``check_material``)."""
    problem: str | None = None

    @property
    def fingers_px(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The two fingers' positions when open."""
        h = 0.5 * self.open_mm / self.mm_per_px
        (u, v), (a, b) = self.centre_px, self.axis_px
        return (u - h * a, v - h * b), (u + h * a, v + h * b)

    def as_json(self) -> dict[str, Any]:
        r = lambda p: [round(p[0], 2), round(p[1], 2)]  # noqa: E731 - a rounding shorthand
        return {"centre_px": r(self.centre_px), "fingers_px": [r(p) for p in self.fingers_px],
                "closing_deg": round(math.degrees(math.atan2(-self.axis_px[1], self.axis_px[0])), 2),
                "open_mm": round(self.open_mm, 2), "mm_per_px": round(self.mm_per_px, 5),
                "approach_mm": self.approach_mm, "grip_width_mm": self.grip_width_mm,
                "contacts_px": None if self.contacts_px is None else [r(p) for p in self.contacts_px],
                "material_mm": None if self.material_mm is None else round(self.material_mm, 2),
                "problem": self.problem}


def open_width_mm(recipe: Recipe) -> float:
    """How far the recipe's fingers open: ``open_width_mm``, else the device's stroke, else 85 mm."""
    gr = recipe.gripper
    if gr.open_width_mm is not None:
        return float(gr.open_width_mm)
    return float(gr.device.stroke_mm) if gr.device is not None else DEFAULT_STROKE_MM


def grasp_in_image(mapping: ActiveMapping, recipe: Recipe, u: float, v: float, angle_deg: float,
                   T_capture: NDArray[np.float64] | None, part: PartPose | None = None) -> GraspImage:
    """The recipe's grasp of a part found at ``(u, v)`` turned ``angle_deg``, in image pixels (``part``: its
    pose when already mapped).

    Raises what ``mapping.map`` raises (``NoCalibration``) or ``UnusableCalibration``."""
    if part is None:
        part = part_pose(mapping, u, v, angle_deg, recipe.plane_z_mm, T_capture, with_uncertainty=False)
    grip = grasp(recipe, part, part.base_yaw_rad + math.radians(recipe.grasp_yaw_deg))
    T_base_grip = part.T_base_part @ grip.T_part_grip
    J = _jacobian(mapping, u, v, recipe.plane_z_mm, T_capture)  # mm per px, 2x2
    Jinv = np.linalg.inv(J)
    p0 = part.T_base_part[:2, 3] * 1e3
    d_px = Jinv @ (T_base_grip[:2, 3] * 1e3 - p0)
    axis_px = Jinv @ T_base_grip[:2, 1]
    axis_px = axis_px / float(np.linalg.norm(axis_px))
    mm_per_px = float(np.linalg.norm(J @ axis_px))
    return GraspImage((u + float(d_px[0]), v + float(d_px[1])), (float(axis_px[0]), float(axis_px[1])), mm_per_px,
                      open_width_mm(recipe), float(recipe.approach_height_mm), recipe.gripper.grip_width_mm)


def _jacobian(mapping: ActiveMapping, u: float, v: float, plane_z_mm: float | None,
              T_capture: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """d(base x, y in mm) / d(u, v in px) of the mapping at ``(u, v)`` on the working plane."""
    pts = [mapping.map(np.array(p), plane_z_mm, T_capture, with_uncertainty=False).xyz_mm[:2]
           for p in ((u, v), (u + PROBE_PX, v), (u, v + PROBE_PX))]
    J = np.stack([(pts[1] - pts[0]) / PROBE_PX, (pts[2] - pts[0]) / PROBE_PX], axis=1)
    if not np.isfinite(J).all() or abs(float(np.linalg.det(J))) < 1e-12:
        from cellctl.pick.pose import UnusableCalibration

        raise UnusableCalibration(f"the active calibration maps the pixels around ({u:.1f}, {v:.1f}) to no plane "
                                  "(a degenerate or non-finite Jacobian): activate another calibration version")
    return J


def check_material(view: GraspImage, model: PartModel, u: float, v: float, angle_deg: float, *,
                   stroke_mm: float, width_tolerance_mm: float | None) -> GraspImage:
    """``view`` with the part's material between its fingers measured on ``model``'s edges drawn at
    ``(u, v, angle_deg)``, and its problem when the grip cannot happen (None: it may). A blob model has
    no edges: returned unchecked."""
    if model.shape is None:
        return view
    pts, _ = model.shape.contour(u, v, angle_deg)
    if len(pts) == 0:
        return view
    c = np.array(view.centre_px)
    a = np.array(view.axis_px)
    rel = pts - c
    t = rel @ a                                  # along the closing axis, px
    s = rel @ np.array([-a[1], a[0]])            # across it, px
    band = max(1.5, _spacing(pts))
    half = 0.5 * view.open_mm / view.mm_per_px
    line = np.abs(s) <= band                     # the model's edges the closing line crosses (the part's chord)
    what = (f"the grasp at ({view.centre_px[0]:.0f}, {view.centre_px[1]:.0f}) px in the teach image (fingers "
            f"closing along {view_yaw(view):.0f} deg on screen)")
    between = (line & (np.abs(t) <= half)).any() or ((line & (t < 0)).any() and (line & (t > 0)).any())
    if not between:  # no edge between the fingers, nor the part reaching past both of them
        return _with(view, None, None, f"{what} closes across no part material: between its fingers (opened "
                     f"{view.open_mm:g} mm) the closing line crosses none of part model {model.name}'s edges; "
                     "move the grasp onto the part (grasp_offset_mm, in the part's frame) or turn it (grasp_yaw_deg)")
    t_lo, t_hi = float(t[line].min()), float(t[line].max())
    contacts_f = ((float(c[0] + t_lo * a[0]), float(c[1] + t_lo * a[1])),
                  (float(c[0] + t_hi * a[0]), float(c[1] + t_hi * a[1])))
    width = (t_hi - t_lo) * view.mm_per_px
    problem = None
    if width > stroke_mm:
        problem = (f"{what} closes across {width:.1f} mm of part {model.name}, wider than the gripper's stroke "
                   f"({stroke_mm:g} mm): its fingers cannot take it there; turn the grasp (grasp_yaw_deg) or move it")
    elif t_lo < -half or t_hi > half:
        problem = (f"{what}: part {model.name} spans {width:.1f} mm of the closing line, from "
                   f"{t_lo * view.mm_per_px:+.1f} to {t_hi * view.mm_per_px:+.1f} mm from the grasp point, beyond the "
                   f"fingers' opening ({view.open_mm:g} mm: {view.open_mm / 2:g} each side): a finger would come "
                   "down on the part; open wider (gripper.open_width_mm) or centre the grasp on it (grasp_offset_mm)")
    elif view.grip_width_mm is not None and width_tolerance_mm is not None and \
            abs(width - view.grip_width_mm) > width_tolerance_mm:
        problem = (f"{what} closes on {width:.1f} mm of part {model.name}, but recipe.gripper.grip_width_mm is "
                   f"{view.grip_width_mm:g} mm (grip check tolerance {width_tolerance_mm:g} mm): every grip would "
                   "fail its check. A part taught turned (its bounding box as the ROI) gives a taught x axis that is "
                   "not the part's: turn the grasp to the part (grasp_yaw_deg) or teach it lying square, or set "
                   "grip_width_mm to the width the fingers really close on")
    return _with(view, contacts_f, width, problem)


def view_yaw(view: GraspImage) -> float:
    """The closing axis's direction on screen, degrees counter-clockwise from +u."""
    return math.degrees(math.atan2(-view.axis_px[1], view.axis_px[0]))


def _with(view: GraspImage, contacts: tuple[tuple[float, float], tuple[float, float]] | None,
          width: float | None, problem: str | None) -> GraspImage:
    return GraspImage(view.centre_px, view.axis_px, view.mm_per_px, view.open_mm, view.approach_mm,
                      view.grip_width_mm, contacts, width, problem)


def _spacing(pts: NDArray[np.float64]) -> float:
    """The edge points' typical spacing (median nearest-neighbour distance), px: a line crossing an edge
    chain passes within about this of one of its points."""
    if len(pts) < 2:
        return 1.0
    sub = pts[:: max(1, len(pts) // 400)]
    d = np.hypot(*(sub[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    d[d == 0] = np.inf
    return float(np.median(d.min(axis=1)))


def taught_grasps(services: Services, recipe: Recipe) -> tuple[list[GraspImage], str | None]:
    """Each of the recipe's models' grasp at its teach pose (the reference point, angle 0), the fingers'
    material checked on its edges; ``([], why)`` when it cannot be drawn (no active calibration maps the
    recipe's camera, or a camera on the arm and no capture pose to map from)."""
    from cellctl.pick.candidate import camera_of

    robot_id = recipe.robot_id or services.config.calibration.robot
    try:
        mapping = active_mapping(services, camera_of(services, recipe, None), robot_id, recipe.calibration,
                                 recipe.plane_z_mm is not None)
    except NoCalibration as exc:
        return [], f"the grasp cannot be drawn in the image: {exc}"
    T_capture = None if recipe.capture_pose_ur is None else g.ur_pose_to_transform(list(recipe.capture_pose_ur))
    if mapping.camera_on_arm and T_capture is None:
        return [], ("the grasp cannot be drawn in the image: the camera rides on the arm and the recipe has no "
                    "capture_pose_ur (where the teach picture was taken)")
    device = recipe.gripper.device
    stroke = float(device.stroke_mm) if device is not None else DEFAULT_STROKE_MM
    tolerance = float(device.width_tolerance_mm) if device is not None and device.kind == "robotiq_2f" else None
    out = []
    try:
        for model in recipe.part_models():
            u, v = model.reference_px
            view = grasp_in_image(mapping, recipe, u, v, 0.0, T_capture)
            out.append(check_material(view, model, u, v, 0.0, stroke_mm=stroke, width_tolerance_mm=tolerance))
    except (NoCalibration, PickError) as exc:
        return [], f"the grasp cannot be drawn in the image: {exc}"
    return out, None
