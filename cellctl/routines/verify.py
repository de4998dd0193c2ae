"""``verify``: one shot of the plate compared with what the active calibration predicts.

With an active hand-eye calibration the plate's pose is predicted from the robot pose
(eye-in-hand: ``inv(T_base_tool @ T_tool_cam) @ T_base_target``; eye-to-hand:
``inv(T_base_cam) @ T_base_tool @ T_tool_target``) and compared with the pose measured in the
image: drift in pixels (RMS over the plate's points) and in mm (RMS over the points, 3D). With
only a camera calibration, the image residual of the measured pose is the check. Pass/fail
against the configured tolerances. Nothing is stored.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration import geometry as g
from calibration.io import handeye_camera
from calibration.pose import estimate_pose
from cellctl.jobs import JobContext
from cellctl.mapping import NoCalibration, active_camera
from cellctl.routines.common import RoutineError, capture, detected_points_m, devices, routine_target
from cellctl.services import Services


class Params(BaseModel):
    """Parameters of ``verify`` (all optional)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, title="VerifyParams")

    camera_id: str | None = Field(None, description="camera to calibrate (default: the config's calibration.camera)")
    robot_id: str | None = Field(None, description="robot to use (default: the config's calibration.robot)")
    target: str | None = Field(None, description="name of a target in the config's targets "
                                                 "(default: calibration.target)")
    tolerance_px: float | None = Field(None, gt=0, le=1000, description="largest drift in the image, px RMS "
                                                               "(default: calibration.verify_tolerance_px)")
    tolerance_mm: float | None = Field(None, gt=0, le=1000, description="largest drift of the plate's points, mm RMS "
                                                               "(default: calibration.verify_tolerance_mm)")


def run(services: Services, ctx: JobContext) -> dict[str, Any]:
    p = Params.model_validate(ctx.params)
    d = services.config.calibration
    camera_id, robot_id = p.camera_id or d.camera, p.robot_id or d.robot
    tol_px, tol_mm = p.tolerance_px or d.verify_tolerance_px, p.tolerance_mm or d.verify_tolerance_mm
    _, target = routine_target(services, p.target)
    found = active_camera(services, camera_id)
    if found is None:
        raise NoCalibration(f"camera {camera_id} has no active calibration to verify")
    cam_cal, camera = found
    he_cal = services.store.active("handeye", camera_id, robot_id)
    # A hand-eye that refined the intrinsics maps through its own camera: its drift is measured
    # through that camera too (the active intrinsics may be a later, different calibration).
    he_camera = handeye_camera(he_cal.result, f"hand-eye calibration {he_cal.id}") if he_cal is not None else None
    if he_camera is not None:
        camera = he_camera
    cam, robot = devices(services, camera_id, robot_id if he_cal is not None else None)
    ctx.report(0.2, "capturing the plate")
    c = capture(cam, robot, target, "verify", ctx)
    if not c.detection.found:
        raise RoutineError(f"the plate is not seen ({c.detection.reason}); put it in view and verify again")
    X = detected_points_m(target, c.detection)
    measured = estimate_pose(camera, X, c.detection.uv)
    out: dict[str, Any] = {"camera_calibration_id": cam_cal.id, "n_points": len(X),
                           "camera_source": "handeye" if he_camera is not None else "camera_calibration",
                           "pose_rms_px": measured.rms_px, "tolerance_px": tol_px, "tolerance_mm": tol_mm}
    if he_cal is None or c.T_base_tool is None:
        out["drift_px"] = measured.rms_px
        out["drift_mm"] = None
        out["passed"] = bool(measured.rms_px <= tol_px)
        out["checked"] = "camera only (no active hand-eye calibration)"
        return out
    he = he_cal.result
    if he["setup"] == "eye-in-hand":
        predicted = g.invert(c.T_base_tool @ np.array(he["T_tool_cam"])) @ np.array(he["T_base_target"])
    else:
        predicted = g.invert(np.array(he["T_base_cam"])) @ c.T_base_tool @ np.array(he["T_tool_target"])
    uv_pred = camera.project(g.transform_points(predicted, X))
    drift_px = float(np.sqrt(np.mean(np.sum((uv_pred - c.detection.uv) ** 2, axis=1))))
    diff = g.transform_points(predicted, X) - g.transform_points(measured.T_cam_target, X)
    drift_mm = float(1000 * np.sqrt(np.mean(np.sum(diff**2, axis=1))))
    out.update({"handeye_calibration_id": he_cal.id, "drift_px": drift_px, "drift_mm": drift_mm,
                "passed": bool(drift_px <= tol_px and drift_mm <= tol_mm),
                "checked": f"camera + hand-eye ({he['setup']})"})
    ctx.report(1.0, "passed" if out["passed"] else "FAILED: the calibration has drifted")
    return out
