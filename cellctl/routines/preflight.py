"""Checks of a routine's parameters against the cell, made before its job starts.

What the cell's configuration and store already decide is answered at once by ``POST
/routines/{name}`` (422 or 409 with what to change) instead of a 202 and a job that fails a moment
later: a camera, robot or target that is not configured, parameters that contradict each other,
an option the cell's setup cannot serve (a tool centre with a camera on the tool), a routine that
needs an active calibration the camera does not have. What only the devices can tell (the plate
not in view, a refused move) still ends the job ``failed``, with the reason.
"""

from __future__ import annotations

from typing import Any

from cellctl.errors import CellctlError
from cellctl.services import Services


class PreflightRefused(CellctlError, ValueError):
    """The routine cannot run on this cell as asked; ``status`` 422 (the request) or 409 (the cell's state)."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code


def preflight(services: Services, name: str, params: Any) -> None:
    """Refuse ``name`` with ``params`` (its validated ``Params``) when the cell already says it cannot run."""
    cfg = services.config
    d = cfg.calibration
    camera_id = getattr(params, "camera_id", None) or d.camera
    if camera_id not in cfg.cameras:
        raise PreflightRefused(422, "unknown_camera", f"no camera {camera_id!r} in the config; configured: "
                                                      f"{', '.join(sorted(cfg.cameras)) or 'none'} (camera_id)")
    uses_robot = not (name == "intrinsics-capture" and getattr(params, "mode", "robot") == "operator")
    robot_id = getattr(params, "robot_id", None) or d.robot
    if uses_robot and name != "verify" and robot_id not in cfg.robots:
        raise PreflightRefused(422, "unknown_robot", f"no robot {robot_id!r} in the config; configured: "
                                                     f"{', '.join(sorted(cfg.robots)) or 'none'} (robot_id)")
    target = getattr(params, "target", None) or d.target
    if target not in cfg.targets:
        raise PreflightRefused(422, "unknown_target", f"no target {target!r} in the config's targets: "
                                                      f"{', '.join(sorted(cfg.targets)) or 'none'} (target)")
    check = _CHECKS.get(name)
    if check is not None:
        check(services, params, camera_id)


def _jog_to_mark(services: Services, p: Any, camera_id: str) -> None:
    if p.tool_centre and services.config.calibration.setup == "eye-in-hand":
        raise PreflightRefused(409, "wrong_setup",
                               "tool_centre needs a fixed camera that sees the gripper, and this cell's camera is on "
                               "the tool (calibration.setup: eye-in-hand; a camera on the tool turns with it): leave "
                               "tool_centre out, or set calibration.setup: eye-to-hand for a fixed camera")
    if p.tcp_mark is not None and p.tcp_mark > p.marks:
        raise PreflightRefused(422, "invalid_params", f"tcp_mark {p.tcp_mark}: only {p.marks} marks will be recorded; "
                                                      f"give 1..{p.marks}")


def _handeye_capture(services: Services, p: Any, camera_id: str) -> None:
    if p.stations > p.max_stations:
        raise PreflightRefused(422, "invalid_params",
                               f"stations ({p.stations}) is more than the max_stations budget ({p.max_stations}); "
                               "raise max_stations or lower stations")
    if getattr(p, "dof", 6) == 4 and getattr(p, "target_z_mm", None) is None:
        raise PreflightRefused(422, "invalid_params",
                               "dof 4 needs target_z_mm: the plate's height in the robot base frame, mm (a robot that "
                               "only turns about z cannot observe it)")
    if services.store.active("camera", camera_id, None) is None:
        raise PreflightRefused(409, "no_active_calibration",
                               f"camera {camera_id} has no active calibration; run intrinsics-capture (POST "
                               "/routines/intrinsics-capture) or add one (POST /calibrations) and activate it "
                               "(POST /calibrations/{id}/activate) first")


def _verify(services: Services, p: Any, camera_id: str) -> None:
    if services.store.active("camera", camera_id, None) is None:
        raise PreflightRefused(409, "no_active_calibration",
                               f"camera {camera_id} has no active calibration to verify; activate one first "
                               "(POST /calibrations/{id}/activate)")


_CHECKS = {"jog-to-mark": _jog_to_mark, "handeye-capture": _handeye_capture, "verify": _verify}
