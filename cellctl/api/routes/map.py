"""``POST /map``: a pixel to a robot-frame point (mm) with its 1-sigma uncertainty (active calibration)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field, field_validator

from calibration import geometry as g
from calibration.measure import MappingError
from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.hints import mapping_message
from cellctl.mapping import NoCalibration, active_mapping, npoint_pose_check
from cellctl.numbers import pixel_problem, point_problem, pose_envelope_problem, pose_ur_problem
from cellctl.strict_types import Num

router = APIRouter(tags=["map"], route_class=EdgeRoute)

# The mapping library's inputs as this route's body fields (its messages name the library's arguments).
FIELDS = {"plane_z_mm": "plane_z_mm (base frame, mm)", "camera": "the camera's calibration (activate one)",
          "robot_pose": "robot_pose_ur [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad]"}


class MapInput(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    u_px: Num = Field(ge=-1e6, le=1e6)
    v_px: Num = Field(ge=-1e6, le=1e6)
    camera_id: str | None = None
    robot_id: str | None = None
    plane_z_mm: Num | None = Field(None, ge=-1e5, le=1e5, description="working plane height in the robot base "
                                                                      "frame, mm (needed with a hand-eye "
                                                                      "calibration)")
    robot_pose_ur: list[Annotated[Num, Field(ge=-1e3, le=1e3)]] | None = Field(
        None, min_length=6, max_length=6, description="T_base_tool at capture (m, rad); default: now")
    calibration: Literal["auto", "handeye", "npoint"] = "auto"

    @field_validator("robot_pose_ur")
    @classmethod
    def _pose_magnitudes(cls, v: list[float] | None) -> list[float] | None:
        problem = None if v is None else pose_ur_problem(v, "robot_pose_ur")
        if problem:
            raise ValueError(problem)
        return v


class MapOutput(BaseModel):
    x_mm: float
    y_mm: float
    z_mm: float | None
    sigma_mm: list[float] = Field(description="1-sigma uncertainty [x, y, z] in mm (the CLI's `cellctl map` "
                                              "answers the same key)")
    calibration_kind: str
    calibration_id: int
    robot_pose_source: str | None
    warning: str | None = None


@router.post("/map", response_model=MapOutput)
def map_pixel(body: MapInput, services: ServicesDep, _: Viewer) -> dict[str, Any]:
    d = services.config.calibration
    camera_id, robot_id = body.camera_id or d.camera, body.robot_id or d.robot
    if camera_id not in services.cell.cameras or robot_id not in services.cell.robots:
        raise ApiError(404, "unknown_device", f"camera {camera_id!r} or robot {robot_id!r} is not configured")
    try:
        mapping = active_mapping(services, camera_id, robot_id, body.calibration, body.plane_z_mm is not None)
    except NoCalibration as exc:
        store = services.store
        he = store.active("handeye", camera_id, robot_id)
        # A hand-eye maps through its own camera, else through the active camera calibration.
        he_can_map = he is not None and (he.result.get("camera") is not None
                                         or store.active("camera", camera_id, None) is not None)
        if body.plane_z_mm is None and he_can_map:
            raise ApiError(422, "plane_z_mm_required",
                           f"the active hand-eye calibration of {camera_id}/{robot_id} maps a pixel to a ray; "
                           "give plane_z_mm, the height of the working plane in the robot base frame (mm), "
                           'e.g. {"u_px": 640, "v_px": 480, "plane_z_mm": 0}') from None
        raise ApiError(409, "no_active_calibration", str(exc)) from None
    source = None
    T = None
    envelope = services.config.robots[robot_id].envelope
    problem = (None if body.robot_pose_ur is None else pose_envelope_problem(
        body.robot_pose_ur, (envelope.x_mm, envelope.y_mm, envelope.z_mm), robot_id, "robot_pose_ur"))
    size = mapping.camera.size if mapping.camera is not None else mapping.calib.get("image_size")
    problem = problem or pixel_problem(body.u_px, body.v_px, tuple(size) if size else None, camera_id)
    if problem:
        raise ApiError(422, "invalid_request", problem)
    if body.robot_pose_ur is not None:
        try:
            T = g.ur_pose_to_transform(body.robot_pose_ur)
        except g.PoseError as exc:
            raise ApiError(422, "invalid_pose", str(exc)) from None
        source = "given"
    elif mapping.kind == "npoint" or mapping.calib.get("setup") == "eye-in-hand":
        T = services.cell.robot(robot_id).ensure_open().state().T_base_tool
        source = "robot state now"
    warning = npoint_pose_check(mapping, T)
    try:
        pt = mapping.map(np.array([body.u_px, body.v_px]), body.plane_z_mm, T)
    except MappingError as exc:
        raise ApiError(422, "cannot_map", mapping_message(exc, FIELDS)) from None
    except NoCalibration as exc:
        raise ApiError(422, "cannot_map", str(exc)) from None
    z = float(pt.xyz_mm[2])
    problem = point_problem([float(c) for c in pt.xyz_mm], [float(c) for c in pt.sigma_mm],
                            z_may_be_unknown=mapping.kind == "npoint" and body.plane_z_mm is None)
    if problem:
        raise ApiError(422, "cannot_map", problem)
    return {"x_mm": float(pt.xyz_mm[0]), "y_mm": float(pt.xyz_mm[1]), "z_mm": z if np.isfinite(z) else None,
            "sigma_mm": [float(s) for s in pt.sigma_mm], "calibration_kind": mapping.kind,
            "calibration_id": mapping.calibration_id, "robot_pose_source": source, "warning": warning}

