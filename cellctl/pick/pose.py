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

This is the one module that turns a match into a pose in the base frame, for parts and fixtures
alike (``part_pose``: ``T_base_part``), and the one gripper-symmetry fold (``fold_yaw``); a pick's
whole candidate (match, part pose, grasp, reachable or not) is ``cellctl.pick.candidate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.handeye import flange_pose_for_feature, tool_offset_vector
from cellctl.mapping import ActiveMapping
from cellctl.motion import pose_json
from cellctl.pick.recipe import PickError, Recipe
from vision.image import wrap_deg

Mat4 = NDArray[np.float64]

AXIS_PROBE_PX = 25.0

__all__ = ["AXIS_PROBE_PX", "Grasp", "PartPose", "UnusableCalibration", "flange_pose", "fold_yaw", "grasp",
           "grip_to_flange", "part_pose", "pick_pose", "pose_json"]


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


@dataclass(frozen=True)
class PartPose:
    """A found part (or fixture) in the base frame: its reference point on the plane ``plane_z_mm``,
    its taught x axis along ``T_base_part``'s x (4x4, metres)."""

    T_base_part: Mat4
    base_yaw_rad: float
    """The taught x axis's direction in the base frame, radians."""
    sigma_mm: list[float]
    """The reference point's 1-sigma (x, y, z), mm; empty when mapped without uncertainty."""


def part_pose(mapping: ActiveMapping, u: float, v: float, angle_deg: float, plane_z_mm: float | None,
              T_capture: Mat4 | None, with_uncertainty: bool = True, pixel_sigma_px: float | None = None) -> PartPose:
    """``T_base_part`` of a match at pixel ``(u, v)`` turned ``angle_deg`` (counter-clockwise on screen):
    the reference point mapped onto ``plane_z_mm`` (None: the mapping's own plane, z = 0 in the pose),
    a second point ``AXIS_PROBE_PX`` along the angle for the taught x axis.

    ``pixel_sigma_px``: the match's own 1-sigma of ``(u, v)`` (px, ``Match.sigma_px``); the point's
    ``sigma_mm`` is the calibration's uncertainty and this pixel noise through the local mm/px scale.
    None or not finite: the calibration's own pixel sigma (``ActiveMapping.map``)."""
    a = math.radians(angle_deg)
    s_px = pixel_sigma_px if pixel_sigma_px is not None and math.isfinite(pixel_sigma_px) and pixel_sigma_px >= 0 \
        else None
    p0 = mapping.map(np.array([u, v]), plane_z_mm, T_capture, with_uncertainty=with_uncertainty, pixel_sigma_px=s_px)
    p1 = mapping.map(np.array([u + AXIS_PROBE_PX * math.cos(a), v - AXIS_PROBE_PX * math.sin(a)]),
                     plane_z_mm, T_capture, with_uncertainty=False)
    if not (np.isfinite(p0.xyz_mm).all() and np.isfinite(p1.xyz_mm).all()):
        raise UnusableCalibration(f"the active calibration maps the match at ({u:.1f}, {v:.1f}) px to no point "
                                  "(not a finite number): activate another calibration version (GET /calibrations)")
    d = p1.xyz_mm[:2] - p0.xyz_mm[:2]
    yaw = math.atan2(d[1], d[0])
    z_mm = plane_z_mm if plane_z_mm is not None else 0.0
    T = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, yaw]),
                         [p0.xyz_mm[0] * 1e-3, p0.xyz_mm[1] * 1e-3, z_mm * 1e-3])
    sigma = [float(x) for x in p0.sigma_mm] if with_uncertainty else []
    return PartPose(T, yaw, sigma)


@dataclass(frozen=True)
class Grasp:
    """How the tool holds a part: ``T_part_grip`` (the part's frame), the pick and approach poses of
    the tool (``T_base_tool``, metres; the flange's when the recipe has a ``tool_centre_offset_mm``)."""

    T_part_grip: Mat4
    T_grip_flange: Mat4
    """The flange in the gripper centre's frame (identity without a ``tool_centre_offset_mm``): the
    commanded pose of a grip at ``T`` is ``T @ T_grip_flange``, at the pick and at the place alike."""
    T_pick: Mat4
    T_approach: Mat4
    gripper_yaw_rad: float


def grip_to_flange(recipe: Recipe) -> Mat4:
    """``T_grip_flange``: the flange pose that puts the gripper's centre at ``T`` is ``T @ T_grip_flange``."""
    if recipe.tool_centre_offset_mm is None:
        return np.eye(4)
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    return flange_pose_for_feature(np.eye(4), tool_offset_vector(recipe.tool_centre_offset_mm, R0))


def flange_pose(recipe: Recipe, T_grip: Mat4) -> Mat4:
    """The flange pose that puts the gripper's centre at ``T_grip`` (``T_grip`` itself without a
    ``tool_centre_offset_mm``)."""
    if recipe.tool_centre_offset_mm is None:
        return T_grip
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    return flange_pose_for_feature(T_grip, tool_offset_vector(recipe.tool_centre_offset_mm, R0))


def grasp(recipe: Recipe, part: PartPose, near_yaw: float) -> Grasp:
    """The recipe's grasp of ``part``: ``Trans(grasp_offset_mm, grasp_z_mm) @ Rz(grasp_yaw + k * symmetry)
    @ R_tool`` in the part's frame, ``k`` folding the tool's yaw to the one nearest ``near_yaw`` (radians)."""
    yaw = fold_yaw(part.base_yaw_rad + math.radians(recipe.grasp_yaw_deg), math.radians(recipe.gripper_symmetry_deg),
                   near_yaw)
    R0 = g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    ox, oy = recipe.grasp_offset_mm
    T_part_grip = g.make_transform(g.rotvec_to_matrix([0.0, 0.0, yaw - part.base_yaw_rad]) @ R0,
                                   [ox * 1e-3, oy * 1e-3, recipe.grasp_z_mm * 1e-3])
    T_pick = flange_pose(recipe, part.T_base_part @ T_part_grip)
    T_approach = T_pick.copy()
    T_approach[2, 3] += recipe.approach_height_mm * 1e-3
    return Grasp(T_part_grip, grip_to_flange(recipe), T_pick, T_approach, yaw)


def pick_pose(mapping: ActiveMapping, recipe: Recipe, u: float, v: float, angle_deg: float,
              T_capture: NDArray[np.float64] | None, current_yaw: float,
              sigma_angle_deg: float = float("nan"), sigma_px: float = float("nan")) -> dict[str, Any]:
    """Gripper pick and approach poses (T_base_tool) for one match, with uncertainty
    (``sigma_angle_deg``: the match's angle 1-sigma; ``sigma_px``: its point's, px, NaN: the calibration's)."""
    part = part_pose(mapping, u, v, angle_deg, recipe.plane_z_mm, T_capture, pixel_sigma_px=sigma_px)
    grip = grasp(recipe, part, current_yaw)
    # (the yaw's 1-sigma once came from sig0 at both ends of the 25 px probe, as if the calibration's
    # error were independent at points 25 px apart: 1.66 deg for a part found to 0.02 deg)
    return {"T_pick": grip.T_pick, "T_approach": grip.T_approach, "part_yaw_deg": wrap_deg(angle_deg),
            "base_yaw_deg": math.degrees(part.base_yaw_rad), "gripper_yaw_deg": math.degrees(grip.gripper_yaw_rad),
            "sigma_mm": part.sigma_mm,
            "sigma_yaw_deg": float(sigma_angle_deg) if math.isfinite(sigma_angle_deg) else None}

