"""The pick flow: grab, locate the recipe's parts, convert each match to a gripper pose, check it.

A match ``(u, v, angle)`` becomes a pose in the robot base frame through the active calibration
(``cellctl.mapping``): the reference point is mapped onto the working plane; the part's x axis
(the image direction at ``angle``, counter-clockwise on screen) is mapped by a second point, which
gives the part's yaw in the base frame (mirrored cameras included). The gripper's pose is the
recipe's grasp offset (part frame, mm) and grasp yaw from there, the gripper's symmetry folding
the yaw to the one nearest the tool's current yaw (a parallel gripper never turns more than 90°),
the tool pointing as the recipe says. Every pose — pick and approach — is checked against the
robot's envelope; a pose outside it is reported ``reachable: false`` and never sent.
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from calibration import geometry as g
from cellctl import metrics
from cellctl.mapping import ActiveMapping, active_mapping, npoint_pose_check
from cellctl.pick.model import PartModel
from cellctl.pick.recognize import recognize
from cellctl.pick.shape import SearchParams
from cellctl.services import Services
from drivers.base import MotionRejected, RobotBase

AXIS_PROBE_PX = 25.0


class PickError(ValueError):
    """The pick cannot be done as asked (no calibration, bad recipe, image of the wrong size...)."""


class SearchSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min_score: float = Field(0.6, gt=0, le=1)
    max_count: int = Field(5, ge=1, le=100)
    angle_start_deg: float = -180.0
    angle_extent_deg: float = Field(360.0, gt=0, le=360)
    roi: tuple[float, float, float, float] | None = None
    timeout_s: float | None = Field(1.0, gt=0, le=60)


class Recipe(BaseModel):
    """What to pick and how (stored versioned in the store under a PLC recipe number)."""

    model_config = ConfigDict(extra="forbid")
    name: str
    models: list[dict[str, Any]] = Field(min_length=1, description="part models (cellctl pick teach output)")
    camera_id: str | None = None
    robot_id: str | None = None
    calibration: Literal["auto", "handeye", "npoint"] = "auto"
    plane_z_mm: float | None = Field(None, description="height of the parts' top face in the base frame, mm")
    grasp_offset_mm: tuple[float, float] = (0.0, 0.0)
    """Grasp point from the part's reference point, in the part's frame (x along its taught x), mm."""
    grasp_z_mm: float = 0.0
    """Tool z above the working plane at the grasp, mm."""
    approach_height_mm: float = Field(50.0, ge=0)
    grasp_yaw_deg: float = 0.0
    gripper_symmetry_deg: float = Field(180.0, gt=0, le=360)
    tool_rotvec_rad: tuple[float, float, float] = (math.pi, 0.0, 0.0)
    """Tool orientation at gripper yaw 0 (default: pointing down, tool x along base x)."""
    speed_m_s: float = Field(0.1, gt=0, le=2)
    search: SearchSettings = SearchSettings()

    def part_models(self) -> list[PartModel]:
        return [PartModel.from_dict(m, f"recipe {self.name} model {k}") for k, m in enumerate(self.models)]


def fold_yaw(yaw: float, symmetry: float, near: float) -> float:
    """The yaw equivalent under the gripper's ``symmetry`` (radians) closest to ``near``."""
    k = round((near - yaw) / symmetry)
    out = yaw + k * symmetry
    return math.atan2(math.sin(out), math.cos(out))


def pick_pose(mapping: ActiveMapping, recipe: Recipe, u: float, v: float, angle_deg: float,
              T_capture: NDArray[np.float64] | None, current_yaw: float) -> dict[str, Any]:
    """Gripper pick and approach poses (T_base_tool) for one match, with uncertainty."""
    z_plane = recipe.plane_z_mm
    a = math.radians(angle_deg)
    p0 = mapping.map(np.array([u, v]), z_plane, T_capture)
    p1 = mapping.map(np.array([u + AXIS_PROBE_PX * math.cos(a), v - AXIS_PROBE_PX * math.sin(a)]),
                     z_plane, T_capture, with_uncertainty=False)
    d = p1.xyz_mm[:2] - p0.xyz_mm[:2]
    part_yaw = math.atan2(d[1], d[0])
    c, s = math.cos(part_yaw), math.sin(part_yaw)
    ox, oy = recipe.grasp_offset_mm
    x_mm = p0.xyz_mm[0] + c * ox - s * oy
    y_mm = p0.xyz_mm[1] + s * ox + c * oy
    z0 = z_plane if z_plane is not None else 0.0
    yaw = fold_yaw(part_yaw + math.radians(recipe.grasp_yaw_deg), math.radians(recipe.gripper_symmetry_deg),
                   current_yaw)
    R = g.rotvec_to_matrix([0.0, 0.0, yaw]) @ g.rotvec_to_matrix(recipe.tool_rotvec_rad)
    T_pick = g.make_transform(R, [x_mm * 1e-3, y_mm * 1e-3, (z0 + recipe.grasp_z_mm) * 1e-3])
    T_approach = T_pick.copy()
    T_approach[2, 3] += recipe.approach_height_mm * 1e-3
    sig0 = p0.sigma_mm
    lever = float(np.linalg.norm(d))
    sigma_yaw = math.degrees(math.sqrt(float(sig0[0] ** 2 + sig0[1] ** 2) * 2) / lever) if lever > 0 else float("nan")
    return {"T_pick": T_pick, "T_approach": T_approach, "part_yaw_deg": math.degrees(part_yaw),
            "gripper_yaw_deg": math.degrees(yaw), "sigma_mm": [float(x) for x in sig0],
            "sigma_yaw_deg": sigma_yaw}


def pose_json(T: NDArray[np.float64]) -> dict[str, float]:
    x, y, z, rx, ry, rz = (float(v) for v in g.transform_to_ur_pose(T))
    return {"x_mm": x * 1e3, "y_mm": y * 1e3, "z_mm": z * 1e3, "rx_rad": rx, "ry_rad": ry, "rz_rad": rz}


def run_pick(services: Services, recipe_id: int, camera_id: str | None = None, move: bool = False,
             who: str = "plc") -> dict[str, Any]:
    """Grab, locate, convert, check; with ``move`` the robot picks the best reachable match."""
    t0 = time.perf_counter()
    stored = services.store.get_recipe(recipe_id)
    recipe = Recipe.model_validate(stored.data)
    d = services.config.calibration
    cam_id = camera_id or recipe.camera_id or d.camera
    robot_id = recipe.robot_id or d.robot
    models = recipe.part_models()
    mapping = active_mapping(services, cam_id, robot_id, recipe.calibration, recipe.plane_z_mm is not None)
    robot: RobotBase = services.cell.robot(robot_id).ensure_open()
    T_capture = robot.state().T_base_tool
    problem = npoint_pose_check(mapping, T_capture)
    if problem:
        raise PickError(problem)
    frame = services.cell.camera(cam_id).ensure_open().grab(timeout_s=5.0)
    t_grab = time.perf_counter()
    size = frame.size
    for m in models:
        if tuple(m.image_size) != size:
            raise PickError(f"part model {m.name} was taught on {m.image_size[0]}x{m.image_size[1]} images; "
                            f"camera {cam_id} delivers {size[0]}x{size[1]}: teach the part on this camera")
    sp = recipe.search
    search = SearchParams(min_score=sp.min_score, max_count=sp.max_count, angle_start_deg=sp.angle_start_deg,
                          angle_extent_deg=sp.angle_extent_deg, roi=sp.roi, timeout_s=sp.timeout_s)
    found = recognize(models, frame.pixels, search)
    t_find = time.perf_counter()
    current_yaw = math.atan2(T_capture[1, 0], T_capture[0, 0])
    picks = []
    for r in found.matches[: sp.max_count]:
        pp = pick_pose(mapping, recipe, r.u_px, r.v_px, r.angle_deg, T_capture, current_yaw)
        reason = None
        try:
            robot.limits.check_pose(pp["T_pick"])
            robot.limits.check_pose(pp["T_approach"])
        except MotionRejected as exc:
            reason = str(exc)
        picks.append({**r.as_dict(), "pick_pose": pose_json(pp["T_pick"]),
                      "approach_pose": pose_json(pp["T_approach"]), "T_base_tool": pp["T_pick"].tolist(),
                      "part_yaw_deg": pp["part_yaw_deg"], "gripper_yaw_deg": pp["gripper_yaw_deg"],
                      "uncertainty": {"sigma_mm": pp["sigma_mm"], "sigma_yaw_deg": pp["sigma_yaw_deg"]},
                      "reachable": reason is None, "not_reachable_reason": reason})
    frame_id = services.frames.add(frame.pixels, [{**p, "part": p["part"]} for p in picks])
    t_done = time.perf_counter()
    metrics.observe_pick(t_done - t0, [p["score"] for p in picks], source=services)
    answer: dict[str, Any] = {
        "recipe_id": recipe_id, "recipe_version": stored.version, "camera_id": cam_id, "robot_id": robot_id,
        "frame_id": frame_id, "image_url": f"/frames/{frame_id}.png", "timed_out": found.timed_out,
        "calibration": {"kind": mapping.kind, "id": mapping.calibration_id},
        "capture_pose": pose_json(T_capture), "picks": picks,
        "latency_ms": {"grab": (t_grab - t0) * 1e3, "find": (t_find - t_grab) * 1e3,
                       "total": (t_done - t0) * 1e3},
        "moved": False,
    }
    if move:
        best = next((p for p in picks if p["reachable"]), None)
        if best is None:
            raise PickError("no reachable pick: nothing found, or every pose is outside the envelope")
        T_pick = np.array(best["T_base_tool"])
        T_app = T_pick.copy()
        T_app[2, 3] += recipe.approach_height_mm * 1e-3
        try:
            for T, why in ((T_app, "approach"), (T_pick, "pick"), (T_app, "retreat")):
                robot.move_linear(T, recipe.speed_m_s)
                services.store.audit(who, "robot.move", robot_id, {"pose": pose_json(T), "why": f"pick {why}"},
                                     "ok")
        except Exception:
            robot.stop()
            raise
        answer["moved"] = True
        answer["picked"] = best
    return answer
