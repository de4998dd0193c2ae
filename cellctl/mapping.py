"""Pixel → robot point through the cell's *active* calibrations (used by ``/map`` and picking).

Preference: an active hand-eye calibration when a working plane height is known; else an active
N-point map. Eye-in-hand needs the robot pose at capture: given, or read from the robot now (and
said so).

A hand-eye maps through **the camera it was solved with** (``he.json["camera"]``, the jointly
refined intrinsics when ``intrinsics_refined``), not through the camera's active intrinsics
calibration: the solution fits the pixels through that camera only (calibration/io/solved_camera.py).
Only a hand-eye file that carries no camera (older, or made elsewhere) maps through the active
camera calibration. Activating a camera calibration that differs from the hand-eye's is guarded
(``POST /calibrations/{id}/activate``: a ``warning`` that the hand-eye must be redone, or 409
``handeye_camera_mismatch`` when the hand-eye carries no camera and its mapping would change).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.io import CameraFileError, camera_from_json, camera_mismatch, handeye_camera, handeye_start_camera
from calibration.measure import RobotPoint, map_handeye, map_npoint
from cellctl.errors import CellctlError
from cellctl.services import Services


class NoCalibration(CellctlError, ValueError):
    """No active calibration can map this camera's pixels to the robot."""


@dataclass
class ActiveMapping:
    """The active calibration chosen for a camera/robot pair, ready to map pixels."""

    kind: str
    calibration_id: int
    calib: dict[str, Any]
    camera: CameraModel | None
    camera_calibration_id: int | None
    """The camera calibration the mapping's camera comes from (a hand-eye's: the one it started from)."""
    camera_source: str = "none"
    """Where ``camera`` comes from: ``"handeye"`` (the camera the hand-eye was solved with),
    ``"camera_calibration"`` (the active intrinsics: a hand-eye file without a camera) or ``"none"``."""

    @property
    def camera_on_arm(self) -> bool:
        """True when the camera rides on the arm: an eye-in-hand hand-eye, or an N-point map taken at a
        capture pose. Its frames then depend on where the robot is."""
        if self.kind == "handeye":
            return bool(self.calib.get("setup") == "eye-in-hand")
        return self.calib.get("capture_pose_ur") is not None

    def map(self, uv_px: NDArray[np.float64], plane_z_mm: float | None,
            T_base_tool_capture: NDArray[np.float64] | None, with_uncertainty: bool = True,
            pixel_sigma_px: float | None = None) -> RobotPoint:
        """The pixel ``uv_px`` (raw, as the camera delivers it) in the base frame (mm) with its 1-sigma.

        ``pixel_sigma_px``: the pixel's own 1-sigma (px, per axis; e.g. a match's ``sigma_px``), propagated
        through the local mm/px scale on top of the calibration's own uncertainty; None: the calibration's
        ``pixel_sigma_px`` (a hand-eye's, 0.1 px when it has none) or the N-point map's default (0.1 px)."""
        if self.kind == "handeye":
            if self.camera is None:
                raise NoCalibration(f"hand-eye calibration {self.calibration_id} has no camera calibration to map "
                                    "through: activate the camera's intrinsics")
            if plane_z_mm is None:
                raise NoCalibration("hand-eye mapping needs the working plane height plane_z_mm (base frame)")
            pose = T_base_tool_capture if self.calib.get("setup") == "eye-in-hand" else None
            return map_handeye(self.calib, uv_px, self.camera, plane_z_mm, pose, pixel_sigma_px=pixel_sigma_px,
                               with_uncertainty=with_uncertainty)
        return map_npoint(self.calib, uv_px, None, plane_z_mm, pixel_sigma_px=pixel_sigma_px)


def active_camera(services: Services, camera_id: str) -> tuple[Any, CameraModel] | None:
    """The camera's active calibration record and its model, or None when none is active."""
    record = services.store.active("camera", camera_id, None)
    if record is None:
        return None
    return record, camera_from_json(record.result, f"calibration {record.id}")


def active_mapping(services: Services, camera_id: str, robot_id: str, prefer: str = "auto",
                   plane_z_known: bool = True) -> ActiveMapping:
    """The active calibration that maps ``camera_id``'s pixels to ``robot_id``'s base frame.

    A hand-eye maps through its own camera (module docstring); without one, through the active
    camera calibration."""
    store = services.store
    he = store.active("handeye", camera_id, robot_id)
    npc = store.active("npoint", camera_id, robot_id)
    he_camera = None
    if he is not None:
        try:
            he_camera = handeye_camera(he.result, f"hand-eye calibration {he.id}")
        except CameraFileError as exc:
            raise NoCalibration(str(exc)) from None
    cam_cal = store.active("camera", camera_id, None) if he is not None and he_camera is None else None
    use_he = (he is not None and (he_camera is not None or cam_cal is not None) and prefer in ("auto", "handeye")
              and plane_z_known)
    if prefer == "handeye" and not use_he:
        raise NoCalibration(f"no active hand-eye + camera calibration for {camera_id}/{robot_id}"
                            + ("" if plane_z_known else " (or no plane_z_mm given)"))
    if use_he and he is not None:
        if he_camera is not None:
            start_id = he.result.get("camera_calibration_id")
            return ActiveMapping("handeye", he.id, he.result, he_camera,
                                 start_id if isinstance(start_id, int) else None, "handeye")
        if cam_cal is None:  # use_he needs the camera's calibration or the hand-eye's own camera
            raise NoCalibration(f"no active camera calibration for {camera_id}: run and activate intrinsics-capture")
        return ActiveMapping("handeye", he.id, he.result, camera_from_json(cam_cal.result, f"calibration {cam_cal.id}"),
                             cam_cal.id, "camera_calibration")
    if npc is not None and prefer in ("auto", "npoint"):
        return ActiveMapping("npoint", npc.id, npc.result, None, None)
    raise NoCalibration(f"no active calibration maps camera {camera_id} to robot {robot_id}: run and activate "
                        "jog-to-mark (N-point), or intrinsics-capture + handeye-capture")


@dataclass(frozen=True)
class HandEyeCameraConflict:
    """An active hand-eye solved with other intrinsics than a camera calibration being activated."""

    message: str
    """What differs and what to do (one sentence)."""
    changes_mapping: bool
    """True when the hand-eye carries no camera of its own: it would map through the new intrinsics
    with an X solved through others (the activation guard refuses that unless forced). False: it
    keeps mapping through its own camera and only needs redoing."""


def handeye_camera_conflicts(services: Services, camera_record: Any) -> list[HandEyeCameraConflict]:
    """The active hand-eyes of ``camera_record``'s camera (a camera calibration about to be
    activated) that were solved with other intrinsics; empty when none was.

    A hand-eye agrees when it started from this very calibration (``camera_calibration_id``), or
    when this camera maps within tolerance like the camera it started from or the one it carries."""
    try:
        new = camera_from_json(camera_record.result, f"calibration {camera_record.id}")
    except CameraFileError:
        return []
    out = []
    for robot_id in sorted(services.config.robots):
        he = services.store.active("handeye", camera_record.camera_id, robot_id)
        if he is None or he.result.get("camera_calibration_id") == camera_record.id:
            continue
        try:
            own = handeye_camera(he.result)
        except CameraFileError:
            own = None
        start = handeye_start_camera(he.result)
        started = he.result.get("camera_calibration_id")
        known = [c for c in (start, own) if c is not None]
        if not known and not isinstance(started, int):
            continue  # a hand-eye file that says nothing of its camera: nothing to compare with
        if any(camera_mismatch(c, new, "it") is None for c in known):
            continue
        ref = start or own
        why = (camera_mismatch(ref, new, f"camera calibration {camera_record.id}") if ref is not None
               else f"it was solved with camera calibration {started}")
        keeps = ("it keeps mapping through the camera it was solved with" if own is not None else
                 "it carries no camera of its own and would map through these intrinsics with a hand-eye solved "
                 "through others")
        out.append(HandEyeCameraConflict(
            f"the active hand-eye calibration {he.id} ({camera_record.camera_id}/{robot_id}) was solved with other "
            f"intrinsics: {why}; {keeps}. Redo the hand-eye with this camera calibration (handeye-capture) and "
            "activate it", own is None))
    return out


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
