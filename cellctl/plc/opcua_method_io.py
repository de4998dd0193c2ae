"""The ``Cell`` object's methods as OPC UA sees them: their arguments, and their answers.

The arguments each method declares (``Pick``, ``PickAndMove``, ``VerifyCalibration``), and how the
request engine's :class:`~cellctl.plc.requests.Outcome` becomes the method's output Variants or, on a
failure, its status code (``STATUS_OF_TEXT``: the error-text index of ``cellctl.plc.requests`` to the
OPC UA status, docs/plc-opcua.md). Pure conversions: nothing here reads the cell or the server.
"""

from __future__ import annotations

import math
from typing import Any

from asyncua import ua

from cellctl.plc.requests import (
    TEXT_BAD_RECIPE,
    TEXT_BUSY,
    TEXT_CANNOT_PICK,
    TEXT_DEVICE,
    TEXT_MOTION_OFF,
    TEXT_NO_CALIBRATION,
    TEXT_RECIPE_RANGE,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
    TEXT_STORE,
    TEXT_TIMEOUT,
    TEXT_UNKNOWN_RECIPE,
    TEXT_VERIFY_FAILED_TO_RUN,
    Outcome,
    pick_sigma,
)

POSE_STRIDE = 8
"""Doubles per pick in ``Poses``: x_mm, y_mm, z_mm, rx_rad, ry_rad, rz_rad, gripper_yaw_deg, score."""
STATUS_OF_TEXT: dict[int, int] = {
    TEXT_UNKNOWN_RECIPE: ua.StatusCodes.BadNotFound,
    TEXT_RECIPE_RANGE: ua.StatusCodes.BadOutOfRange,
    TEXT_NO_CALIBRATION: ua.StatusCodes.BadInvalidState,
    TEXT_BAD_RECIPE: ua.StatusCodes.BadInvalidState,
    TEXT_CANNOT_PICK: ua.StatusCodes.BadInvalidState,
    TEXT_DEVICE: ua.StatusCodes.BadResourceUnavailable,
    TEXT_VERIFY_FAILED_TO_RUN: ua.StatusCodes.BadResourceUnavailable,
    TEXT_TIMEOUT: ua.StatusCodes.BadTimeout,
    TEXT_ROBOT_STOPPED: ua.StatusCodes.BadRequestNotAllowed,
    TEXT_ROBOT_BUSY: ua.StatusCodes.BadLocked,
    TEXT_BUSY: ua.StatusCodes.BadTooManyOperations,
    TEXT_MOTION_OFF: ua.StatusCodes.BadNotExecutable,
    TEXT_STORE: ua.StatusCodes.BadResourceUnavailable,
}


def argument(name: str, vtype: ua.VariantType, description: str, array: bool = False) -> ua.Argument:
    """One declared input or output of a method (a scalar, or a one-dimensional array)."""
    a = ua.Argument()
    a.Name = name
    a.DataType = ua.NodeId(ua.Int32(vtype.value))
    a.ValueRank = 1 if array else -1
    a.ArrayDimensions = [0] if array else []
    a.Description = ua.LocalizedText(description)
    return a


def pick_signature(move: bool) -> tuple[list[ua.Argument], list[ua.Argument]]:
    """``Pick``'s inputs and outputs; with ``move``, ``PickAndMove``'s (its outputs end with PickedIndex)."""
    outputs = [
        argument("Count", ua.VariantType.Int32, "number of picks, best first"),
        argument("Poses", ua.VariantType.Double, "8 per pick: x_mm, y_mm, z_mm, rx_rad, ry_rad, rz_rad, "
                                                 "gripper_yaw_deg, score", array=True),
        argument("Reachable", ua.VariantType.Boolean, "per pick: inside the robot's envelope", array=True)]
    if move:
        outputs.append(argument("PickedIndex", ua.VariantType.Int32, "index in Poses of the pick the robot made"))
    return [argument("RecipeId", ua.VariantType.Int32, "recipe number 0..65535")], outputs


def verify_signature() -> list[ua.Argument]:
    """``VerifyCalibration``'s outputs (it has no input)."""
    return [argument("Passed", ua.VariantType.Boolean, "the active calibration is within tolerance"),
            argument("DriftPx", ua.VariantType.Double, "RMS drift of the plate's points, pixels"),
            argument("DriftMm", ua.VariantType.Double, "RMS drift in 3D, mm (NaN: no hand-eye calibration)")]


def status_code(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def failed_status(out: Outcome) -> ua.StatusCode:
    """The status code a failed request answers (BadInternalError for an error without its own)."""
    return status_code(STATUS_OF_TEXT.get(out.text_index, ua.StatusCodes.BadInternalError))


def sigma_arrays(out: Outcome) -> tuple[list[float], list[float]]:
    """The picks' position 1-sigma (mm) and yaw 1-sigma (degrees) in ``Poses``' order; NaN: not known."""
    sigmas = [pick_sigma(p) for p in out.picks]
    return ([math.nan if mm is None else mm for mm, _ in sigmas],
            [math.nan if deg is None else deg for _, deg in sigmas])


def pick_outputs(out: Outcome, move: bool) -> list[ua.Variant]:
    """A successful Pick's outputs (Count, Poses, Reachable), and PickAndMove's PickedIndex (-1: none)."""
    poses: list[float] = []
    reachable: list[bool] = []
    for p in out.picks:
        q = p["pick_pose"]
        poses += [q["x_mm"], q["y_mm"], q["z_mm"], q["rx_rad"], q["ry_rad"], q["rz_rad"],
                  float(p["gripper_yaw_deg"]), float(p["score"])]
        reachable.append(bool(p["reachable"]))
    answer = [ua.Variant(len(out.picks), ua.VariantType.Int32),
              ua.Variant([float(x) for x in poses], ua.VariantType.Double),
              ua.Variant(reachable, ua.VariantType.Boolean)]
    if move:
        picked = -1 if out.picked_index is None else out.picked_index
        answer.append(ua.Variant(picked, ua.VariantType.Int32))
    return answer


def verify_outputs(verify: dict[str, Any]) -> list[ua.Variant]:
    """VerifyCalibration's outputs (Passed, DriftPx, DriftMm; NaN: not measured) from the request's answer."""
    drift_mm = verify.get("drift_mm")
    return [ua.Variant(bool(verify.get("passed")), ua.VariantType.Boolean),
            ua.Variant(float(verify.get("drift_px", math.nan)), ua.VariantType.Double),
            ua.Variant(float(drift_mm) if drift_mm is not None else math.nan,
                       ua.VariantType.Double)]
