"""``intrinsics-capture`` with the robot: views planned from what was seen, until the verdict is ok.

The views come from ``ViewPlanner`` (probe shifts, the four image corners in a closed loop, tilts
about both camera axes, other distances); with ``calibration.setup: eye-to-hand`` (a fixed camera,
the plate on the tool) from ``FixedCameraViewPlanner``, which moves the plate instead of the camera.
After ``views`` good views the camera is calibrated; while its verdict is not ok and the
``max_views`` budget lasts, views that address the verdict's problems are added and it is
calibrated again. A shift probe that does not move the plate in the image ends the routine: the
robot carries neither the camera nor the plate. The result says which coverage is still missing.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol

import numpy as np

from calibration.intrinsics import calibrate
from calibration.targets import Target
from cellctl.jobs import JobContext
from cellctl.routines.common import Capture, RoutineError, approximate_camera, capture, move, pivot_point, target_pose
from cellctl.routines.view_plan import Mat4, ViewPlanner
from cellctl.routines.view_plan_fixed import FixedCameraViewPlanner
from cellctl.services import Services
from drivers.base import CameraBase, MotionRejected, RobotBase

STILL_PLATE_FRACTION = 0.01
"""A shift probe must move the plate by at least this fraction of the image width (it aims at ~0.15)."""


class CaptureParams(Protocol):
    views: int
    max_views: int
    max_tilt_deg: float
    speed_m_s: float | None


class PlannedCapture:
    """One run of the planned capture loop (see the module docstring)."""

    def __init__(self, services: Services, ctx: JobContext, robot: RobotBase, cam: CameraBase, target: Target,
                 params: Any, good: Callable[[Capture], bool], first: Capture, caps: list[Capture]) -> None:
        self.services, self.ctx, self.robot, self.cam, self.target = services, ctx, robot, cam, target
        self.p: CaptureParams = params
        self.good = good
        self.caps = caps
        self.first = first
        self.speed = params.speed_m_s or services.config.calibration.speed_m_s
        self.model = params.model or services.config.calibration.model
        self.attempts = 1
        self.rejected = 0
        if first.T_base_tool is None:
            raise RoutineError("the start view has no robot pose; the robot must report its pose")
        w, h = first.frame.size
        self.approx = approximate_camera(w, h)
        T_cam_target = target_pose(self.approx, target, first.detection)
        centre = target.points().xyz_m.mean(axis=0)
        distance = float((T_cam_target[:3, :3] @ centre + T_cam_target[:3, 3])[2])
        self.fixed_camera = services.config.calibration.setup == "eye-to-hand"
        self.planner: ViewPlanner
        if self.fixed_camera:
            self.planner = FixedCameraViewPlanner(first.T_base_tool, first.detection.uv, (w, h), centre, distance,
                                                  params.max_tilt_deg, frame_scale=_frame_scale(target),
                                                  centre_target_m=centre)
        else:
            self.planner = ViewPlanner(first.T_base_tool, first.detection.uv, (w, h),
                                       pivot_point(first.T_base_tool, T_cam_target, target), distance,
                                       params.max_tilt_deg, frame_scale=_frame_scale(target))
        self.planner.observe(first.T_base_tool, first.detection.uv, True, "start", T_cam_target)

    def run(self) -> tuple[Any, int]:
        """Capture, calibrate, and add views until the verdict is ok or the budget is spent."""
        self._try(self.planner.plan(), stop_at_views=True)
        result = self._calibrate()
        round_k = 0
        while not result.verdict.get("ok") and self.attempts < self.p.max_views:
            codes = [q["code"] for q in result.verdict.get("problems", [])]
            self.ctx.report(min(0.9, self.attempts / self.p.max_views),
                            f"verdict not ok ({', '.join(codes)}): adding views")
            before = self.attempts
            self._try(self.planner.more(codes, round_k), stop_at_views=False)
            round_k += 1
            if self.attempts == before:
                break
            result = self._calibrate()
        result.verdict["coverage_missing"] = {"corners": self.planner.missing_corners(),
                                              "border": self.planner.missing_border(),
                                              "views_tried": self.attempts, "budget": self.p.max_views}
        return result, self.rejected

    def _calibrate(self) -> Any:
        self.ctx.check_cancelled()
        self.ctx.report(0.92, f"calibrating {self.model} from {len(self.caps)} views")
        return calibrate([c.detection for c in self.caps], self.target, self.model)

    def _try(self, poses: Iterable[tuple[str, Mat4]], stop_at_views: bool) -> None:
        for purpose, T in poses:
            if self.attempts >= self.p.max_views or (stop_at_views and len(self.caps) >= self.p.views):
                return
            self.attempts += 1
            try:
                self.robot.limits.check_pose(T)
            except MotionRejected as exc:
                self.rejected += 1
                self.planner.observe(T, np.zeros((0, 2)), False, purpose)
                self.ctx.report(self._progress(), f"view {self.attempts} ({purpose}): skipped, unreachable ({exc})")
                continue
            move(self.services, self.ctx, self.robot, T, self.speed, f"intrinsics-capture {purpose}")
            c = capture(self.cam, self.robot, self.target, f"view{self.attempts:02d}", self.ctx)
            ok = self.good(c)
            self.planner.observe(T, c.detection.uv, ok, purpose,
                                 target_pose(self.approx, self.target, c.detection) if ok else None)
            if ok and purpose.startswith("probe ") and not purpose.startswith("probe tilt"):
                self._check_moved(c, purpose)
            if ok:
                self.caps.append(c)
            else:
                self.rejected += 1
            self.ctx.report(self._progress(), f"view {self.attempts} ({purpose}): "
                            + ("ok" if ok else f"rejected ({c.detection.reason or 'too few points'})"))

    def _check_moved(self, c: Capture, purpose: str) -> None:
        """A shift probe that leaves the plate where it was: the robot does not move what the camera sees."""
        moved_px = float(np.linalg.norm(c.detection.uv.mean(axis=0) - self.first.detection.uv.mean(axis=0)))
        if moved_px < STILL_PLATE_FRACTION * self.first.frame.size[0]:
            where = ("the plate must be on the tool, facing the camera (calibration.setup: eye-to-hand)"
                     if self.fixed_camera else "the camera must be on the tool (calibration.setup: eye-in-hand)")
            raise RoutineError(f"the plate moved {moved_px:.1f} px in the image when the robot moved ({purpose}): "
                               f"the robot carries neither the camera nor the plate, and {where}. A plate that lies "
                               "still in front of a fixed camera is calibrated with mode: operator (present it "
                               "by hand in each view)")

    def _progress(self) -> float:
        return min(0.9, len(self.caps) / max(self.p.views, 1) * 0.9)


def _frame_scale(target: Target) -> float:
    """How much wider the plate's frame is than its points (1 for a target without a frame)."""
    extent = getattr(target, "extent_m", None)
    if extent is None:
        return 1.0
    x0, y0, x1, y1 = extent()
    xyz = target.points().xyz_m
    span = float(max(np.ptp(xyz[:, 0]), np.ptp(xyz[:, 1])))
    return float(max(x1 - x0, y1 - y0)) / span if span > 0 else 1.0


