"""A match in the image -> the gripper's pick and approach poses in the robot base frame.

A match ``(u, v, angle)`` becomes a pose in the robot base frame through the active calibration
(``cellctl.mapping``): the reference point is mapped onto the working plane; the part's x axis
(the image direction at ``angle``, counter-clockwise on screen) is mapped by a second point, which
gives the part's yaw in the base frame, ``base_yaw_deg`` (mirrored cameras included). The gripper's
pose is the recipe's grasp offset (part frame, mm) and grasp yaw from there, the gripper's symmetry
folding the yaw to the one nearest the tool's current yaw (a parallel gripper never turns more than
90 deg), the tool pointing as the recipe says.

``part_yaw_deg`` is the part's rotation relative to the teach image, counter-clockwise on screen
(the match's angle: 0 means it lies as when taught). Its 1-sigma, ``sigma_yaw_deg``, is the match's
own (``Match.sigma_angle_deg``, from the fit); the calibration turns every part alike, so its
orientation error is a constant offset of ``base_yaw_deg`` that belongs to the calibration's
uncertainty, not to each pick's.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.handeye import flange_pose_for_feature, tool_offset_vector
from cellctl.mapping import ActiveMapping
from cellctl.pick.recipe import PickError, Recipe
from vision.image import wrap_deg

AXIS_PROBE_PX = 25.0


class UnusableCalibration(PickError):
    """The active calibration maps a found part to no pose (a non-finite number): the service answers 409
    ``calibration_unusable`` naming it; activate another version (a calibration stored before the store's
    checks, or damaged, can do this; ``POST /calibrations`` refuses such files now)."""


def fold_yaw(yaw: float, symmetry: float, near: float) -> float:
    """The yaw equivalent under the gripper's ``symmetry`` (radians) closest to ``near``."""
    if not (math.isfinite(yaw) and math.isfinite(symmetry) and symmetry > 0 and math.isfinite(near)):
        raise UnusableCalibration(f"the part's yaw ({yaw:g} rad) or the tool's ({near:g} rad) is not a finite number: "
                                  "the active calibration cannot map this image; activate another calibration "
                                  "version (GET /calibrations)")
    k = round((near - yaw) / symmetry)
    out = yaw + k * symmetry
    return math.atan2(math.sin(out), math.cos(out))


def pick_pose(mapping: ActiveMapping, recipe: Recipe, u: float, v: float, angle_deg: float,
              T_capture: NDArray[np.float64] | None, current_yaw: float,
              sigma_angle_deg: float = float("nan")) -> dict[str, Any]:
    """Gripper pick and approach poses (T_base_tool) for one match, with uncertainty
    (``sigma_angle_deg``: the match's angle 1-sigma)."""
    z_plane = recipe.plane_z_mm
    a = math.radians(angle_deg)
    p0 = mapping.map(np.array([u, v]), z_plane, T_capture)
    p1 = mapping.map(np.array([u + AXIS_PROBE_PX * math.cos(a), v - AXIS_PROBE_PX * math.sin(a)]),
                     z_plane, T_capture, with_uncertainty=False)
    if not (np.isfinite(p0.xyz_mm).all() and np.isfinite(p1.xyz_mm).all()):
        raise UnusableCalibration(f"the active calibration maps the part found at ({u:.1f}, {v:.1f}) px to no point "
                                  "(not a finite number): activate another calibration version (GET /calibrations)")
    d = p1.xyz_mm[:2] - p0.xyz_mm[:2]
    part_yaw = math.atan2(d[1], d[0])
    c, s = math.cos(part_yaw), math.sin(part_yaw)
    ox, oy = recipe.grasp_offset_mm
    x_mm = p0.xyz_mm[0] + c * ox - s * oy
    y_mm = p0.xyz_mm[1] + s * ox + c * oy
    z0 = z_plane if z_plane is not None else 0.0
    yaw = fold_yaw(part_yaw + math.radians(recipe.grasp_yaw_deg), math.radians(recipe.gripper_symmetry_deg),
                   current_yaw)
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    R = g.rotvec_to_matrix([0.0, 0.0, yaw]) @ R0
    T_pick = g.make_transform(R, [x_mm * 1e-3, y_mm * 1e-3, (z0 + recipe.grasp_z_mm) * 1e-3])
    if recipe.tool_centre_offset_mm is not None:
        # The pose found is where the gripper's centre must be; the robot is commanded by its flange.
        T_pick = flange_pose_for_feature(T_pick, tool_offset_vector(recipe.tool_centre_offset_mm, R0))
    T_approach = T_pick.copy()
    T_approach[2, 3] += recipe.approach_height_mm * 1e-3
    sig0 = p0.sigma_mm
    # (the yaw's 1-sigma once came from sig0 at both ends of the 25 px probe, as if the calibration's
    # error were independent at points 25 px apart: 1.66 deg for a part found to 0.02 deg)
    return {"T_pick": T_pick, "T_approach": T_approach, "part_yaw_deg": wrap_deg(angle_deg),
            "base_yaw_deg": math.degrees(part_yaw), "gripper_yaw_deg": math.degrees(yaw),
            "sigma_mm": [float(x) for x in sig0],
            "sigma_yaw_deg": float(sigma_angle_deg) if math.isfinite(sigma_angle_deg) else None}


def pose_json(T: NDArray[np.float64]) -> dict[str, float]:
    x, y, z, rx, ry, rz = (float(v) for v in g.transform_to_ur_pose(T))
    return {"x_mm": x * 1e3, "y_mm": y * 1e3, "z_mm": z * 1e3, "rx_rad": rx, "ry_rad": ry, "rz_rad": rz}
