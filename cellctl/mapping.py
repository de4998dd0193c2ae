"""Pixel → robot point through the cell's *active* calibrations (used by ``/map`` and picking).

Preference: an active hand-eye calibration (with the camera's active intrinsics) when a working
plane height is known; else an active N-point map. Eye-in-hand needs the robot pose at capture:
given, or read from the robot now (and said so).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.io import camera_from_json
from calibration.measure import RobotPoint, map_handeye, map_npoint
from cellctl.services import Services


class NoCalibration(ValueError):
    """No active calibration can map this camera's pixels to the robot."""


@dataclass
class ActiveMapping:
    """The active calibration chosen for a camera/robot pair, ready to map pixels."""

    kind: str
    calibration_id: int
    calib: dict[str, Any]
    camera: CameraModel | None
    camera_calibration_id: int | None

    @property
    def camera_on_arm(self) -> bool:
        """True when the camera rides on the arm: an eye-in-hand hand-eye, or an N-point map taken at a
        capture pose. Its frames then depend on where the robot is."""
        if self.kind == "handeye":
            return bool(self.calib.get("setup") == "eye-in-hand")
        return self.calib.get("capture_pose_ur") is not None

    def map(self, uv_px: NDArray[np.float64], plane_z_mm: float | None,
            T_base_tool_capture: NDArray[np.float64] | None, with_uncertainty: bool = True) -> RobotPoint:
        if self.kind == "handeye":
            if self.camera is None:
                raise NoCalibration(f"hand-eye calibration {self.calibration_id} has no camera calibration to map "
                                    "through: activate the camera's intrinsics")
            if plane_z_mm is None:
                raise NoCalibration("hand-eye mapping needs the working plane height plane_z_mm (base frame)")
            pose = T_base_tool_capture if self.calib.get("setup") == "eye-in-hand" else None
            return map_handeye(self.calib, uv_px, self.camera, plane_z_mm, pose, with_uncertainty=with_uncertainty)
        return map_npoint(self.calib, uv_px, None, plane_z_mm)


def active_camera(services: Services, camera_id: str) -> tuple[Any, CameraModel] | None:
    """The camera's active calibration record and its model, or None when none is active."""
    record = services.store.active("camera", camera_id, None)
    if record is None:
        return None
    return record, camera_from_json(record.result, f"calibration {record.id}")


def active_mapping(services: Services, camera_id: str, robot_id: str, prefer: str = "auto",
                   plane_z_known: bool = True) -> ActiveMapping:
    store = services.store
    cam_cal = store.active("camera", camera_id, None)
    he = store.active("handeye", camera_id, robot_id)
    npc = store.active("npoint", camera_id, robot_id)
    use_he = he is not None and cam_cal is not None and prefer in ("auto", "handeye") and plane_z_known
    if prefer == "handeye" and not use_he:
        raise NoCalibration(f"no active hand-eye + camera calibration for {camera_id}/{robot_id}"
                            + ("" if plane_z_known else " (or no plane_z_mm given)"))
    if use_he and he is not None and cam_cal is not None:
        return ActiveMapping("handeye", he.id, he.result, camera_from_json(cam_cal.result, f"calibration {cam_cal.id}"),
                             cam_cal.id)
    if npc is not None and prefer in ("auto", "npoint"):
        return ActiveMapping("npoint", npc.id, npc.result, None, None)
    raise NoCalibration(f"no active calibration maps camera {camera_id} to robot {robot_id}: run and activate "
                        "jog-to-mark (N-point), or intrinsics-capture + handeye-capture")


def npoint_pose_check(mapping: ActiveMapping, T_base_tool_now: NDArray[np.float64] | None,
                      tolerance_mm: float = 1.0) -> str | None:
    """An N-point map holds only at its capture pose (eye-in-hand): say when the robot is elsewhere."""
    pose = mapping.calib.get("capture_pose_ur")
    if mapping.kind != "npoint" or pose is None or T_base_tool_now is None:
        return None
    T_cap = g.ur_pose_to_transform(pose)
    rot, trans = g.transform_error(T_cap, T_base_tool_now)
    if trans * 1e3 > tolerance_mm or np.degrees(rot) > 0.1:
        return (f"the robot is {trans * 1e3:.1f} mm / {np.degrees(rot):.2f} deg away from the pose the N-point map "
                f"was taught at; move it back to {np.round(pose, 4).tolist()} (UR form) before mapping")
    return None
