"""One path from a match to a pick: ``locate`` grabs, searches and turns every match into a typed
``PickCandidate`` once (the match, ``T_base_part`` and its uncertainty, the grasp, reachable or not).

REST and the PLC front ends (``cellctl.pick.flow.run_pick``, its JSON answer ``Located.answer()``)
and production (``cellctl.production.vision``) all take their candidates from here; nothing reads
``u_px``/``v_px``/``angle_deg`` back out of an answer to compute a pose again. Poses are
``T_base_tool`` (4x4, metres); the match's pixels and angle follow ``cellctl.pick``'s conventions.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellctl.arm_view import ArmView, arm_view
from cellctl.mapping import ActiveMapping, active_mapping, npoint_pose_check
from cellctl.pick.fixture import FixtureSpec, locate_fixture
from cellctl.pick.frames import match_contours
from cellctl.pick.grasp_view import grasp_in_image
from cellctl.pick.pose import grasp, part_pose, pose_json
from cellctl.pick.recipe import PickError, Recipe
from cellctl.services import Services
from drivers.base import MotionRejected, RobotBase
from vision.image import wrap_deg
from vision.recognize import Recognition, recognize
from vision.types import SearchParams

Mat4 = NDArray[np.float64]


@dataclass
class PickCandidate:
    """One found part, computed once: the match, its pose, the grasp, and whether the robot may go there.

    Plain values (no computed properties): whoever takes the candidate further (production's place)
    reads them without coming back into ``cellctl.pick``."""

    match: Recognition
    T_base_part: Mat4
    """The part's reference point on the plane, its taught x axis along x (4x4, metres, base frame)."""
    sigma_mm: list[float]
    """The reference point's 1-sigma (x, y, z), mm: the calibration's uncertainty and the match's own pixel
    1-sigma (``match.sigma_px``; the calibration's pixel sigma when the match has none) through the local scale."""
    sigma_yaw_deg: float | None
    """The part's yaw 1-sigma (the match's own angle sigma), degrees; None when the search gave none."""
    base_yaw_deg: float
    """The part's taught x axis in the base frame, degrees."""
    T_part_grip: Mat4
    """The gripper centre in the part's frame (the recipe's grasp, folded to the tool's nearest yaw)."""
    T_grip_flange: Mat4
    """The commanded flange in the gripper centre's frame (identity without a tool centre offset)."""
    T_pick: Mat4
    T_approach: Mat4
    gripper_yaw_deg: float
    refused: tuple[str, str] | None = None
    """(which pose, why) when the pick or its approach is outside the robot's envelope; None: reachable."""
    problem: str | None = None
    """Why this part is not to be picked (a refused pose; production adds a neighbour too close); None: it may be."""
    grasp_px: dict[str, Any] | None = None
    """The grasp drawn in the picture (``cellctl.pick.grasp_view.GraspImage.as_json``: the gripper centre, the
    open fingers, the closing direction); None when the calibration gives no local scale there."""

    @property
    def reachable(self) -> bool:
        return self.refused is None

    def as_json(self) -> dict[str, Any]:
        """The pick answer's entry for this part (``POST /pick``, the PLC's picks)."""
        return {**self.match.as_dict(), "pick_pose": pose_json(self.T_pick),
                "approach_pose": pose_json(self.T_approach), "T_base_tool": self.T_pick.tolist(),
                "part_yaw_deg": wrap_deg(self.match.angle_deg), "base_yaw_deg": self.base_yaw_deg,
                "gripper_yaw_deg": self.gripper_yaw_deg,
                "uncertainty": {"sigma_mm": self.sigma_mm, "sigma_yaw_deg": self.sigma_yaw_deg},
                "reachable": self.reachable, "not_reachable_reason": None if self.refused is None else self.refused[1],
                "grasp_px": self.grasp_px}


def candidate(mapping: ActiveMapping, recipe: Recipe, match: Recognition, T_capture: Mat4 | None, near_yaw: float,
              robot: RobotBase) -> PickCandidate:
    """One match's candidate: its pose, the recipe's grasp folded nearest ``near_yaw`` (radians), both
    the pick and its approach checked against ``robot``'s envelope."""
    # The point's sigma: the calibration's uncertainty plus the match's own pixel 1-sigma (rim-refined or not)
    # through the local mm/px scale (the calibration's pixel sigma when the match gives none).
    part = part_pose(mapping, match.u_px, match.v_px, match.angle_deg, recipe.plane_z_mm, T_capture,
                     pixel_sigma_px=float(match.sigma_px))
    grip = grasp(recipe, part, near_yaw)
    refused = None
    for T, what in ((grip.T_pick, "pick"), (grip.T_approach, "pre-pick")):
        try:
            robot.limits.check_pose(T)
        except MotionRejected as exc:
            refused = (what, str(exc))
            break
    problem = None if refused is None else f"the {refused[0]} pose is refused: {refused[1]}"
    sigma_yaw = float(match.sigma_angle_deg)
    try:
        drawn: dict[str, Any] | None = grasp_in_image(mapping, recipe, match.u_px, match.v_px, match.angle_deg,
                                                      T_capture, part).as_json()
    except PickError:  # no local scale at the match (UnusableCalibration): the pose above was mapped, the drawing not
        drawn = None
    return PickCandidate(match, part.T_base_part, part.sigma_mm, sigma_yaw if math.isfinite(sigma_yaw) else None,
                         math.degrees(part.base_yaw_rad), grip.T_part_grip, grip.T_grip_flange, grip.T_pick,
                         grip.T_approach, math.degrees(grip.gripper_yaw_rad), refused, problem, drawn)


def _ticks(value: Any) -> int | None:
    return None if value is None else int(value)


def _arm_in(arm: ArmView | None, roi: Any) -> str | None:
    """What of the arm lies in the search region ``roi``, in words (None: nothing or no arm known)."""
    if arm is None:
        return None
    return arm.what if arm.share_of(roi) > 0 else None


@dataclass
class Located:
    """What one picture found: the candidates (the search's order), the frame and how long it took."""

    recipe_id: int
    recipe_version: int
    camera_id: str
    robot_id: str
    mapping: ActiveMapping
    T_capture: Mat4
    candidates: list[PickCandidate]
    frame_id: int
    reason: str | None
    timed_out: bool
    rejected: list[dict[str, Any]] = field(default_factory=list)
    latency_ms: dict[str, float] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    """The calibration that mapped the matches: ``{"kind", "id"}``."""
    arm: ArmView | None = None
    """The arm's region in the picture (a fixed camera with an eye-to-hand hand-eye), its matches dropped."""

    search_roi: Any = None
    """The recipe's ``search.roi`` the picture was searched in (None: the whole image)."""
    arm_in_view: str | None = None
    """What of the arm the picture shows in the search region, in words (None: nothing); a plain value,
    computed once in :func:`locate`, so a caller reading it does not come back into this package."""
    encoder_ticks: int | None = None
    """A belt's encoder count latched at the frame's exposure (``Frame.meta["encoder_ticks"]``); None: none."""
    T_base_fixture: Mat4 | None = None
    """The fixture asked for (``locate(..., fixture=)``) in the base frame (4x4, metres); None: not asked
    or not found."""
    fixture: dict[str, Any] | None = None
    """What the fixture search found (``score``, ``u_px``, ``v_px``, ``angle_deg``) or its ``reason``; None:
    not asked."""

    def answer(self) -> dict[str, Any]:
        """The pick answer (``POST /pick``; the PLC front ends read the same)."""
        return {
            "recipe_id": self.recipe_id, "recipe_version": self.recipe_version, "camera_id": self.camera_id,
            "robot_id": self.robot_id, "frame_id": self.frame_id, "image_url": f"/frames/{self.frame_id}.png",
            "timed_out": self.timed_out, "calibration": self.calibration, "capture_pose": pose_json(self.T_capture),
            "picks": [c.as_json() for c in self.candidates], "reason": self.reason, "rejected": self.rejected,
            "latency_ms": self.latency_ms, "moved": False, "arm_in_view": self.arm_in_view,
        }


def camera_of(services: Services, recipe: Recipe, camera_id: str | None) -> str:
    """The camera a pick looks through: the request's, else the recipe's, else the config's calibration camera."""
    return camera_id or recipe.camera_id or services.config.calibration.camera


def search_params(recipe: Recipe) -> SearchParams:
    sp = recipe.search
    return SearchParams(min_score=sp.min_score, max_count=sp.max_count, angle_start_deg=sp.angle_start_deg,
                        angle_extent_deg=sp.angle_extent_deg, roi=sp.roi, timeout_s=sp.timeout_s,
                        polarity=sp.polarity, greediness=sp.greediness, scale_min=sp.scale_range[0],
                        scale_max=sp.scale_range[1], mirrored=sp.mirrored, max_overlap=sp.max_overlap,
                        min_surround=sp.min_surround)


def locate(services: Services, recipe_id: int, version: int, recipe: Recipe, camera_id: str | None,
           robot: RobotBase, near_yaw: float | None = None, fixture: FixtureSpec | None = None) -> Located:
    """Grab, search the recipe's parts, and turn each match into a ``PickCandidate`` (at most
    ``search.max_count``); the frame is kept in ``services.frames`` with its matches. ``near_yaw``: the
    tool yaw (radians) each grasp is folded nearest to (default: the tool's yaw at the grab). ``fixture``: a
    fixture to find in the same frame (production's located place; ``Located.T_base_fixture``)."""
    t0 = time.perf_counter()
    cam_id = camera_of(services, recipe, camera_id)
    models = recipe.part_models()
    mapping = active_mapping(services, cam_id, robot.robot_id, recipe.calibration, recipe.plane_z_mm is not None)
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
    found = recognize(models, frame.pixels, search_params(recipe))
    t_find = time.perf_counter()
    near = math.atan2(T_capture[1, 0], T_capture[0, 0]) if near_yaw is None else near_yaw
    # A fixed camera sees the arm (and the plate it may carry) where it stood at the grab: a match there is
    # the arm's, not a part (cellctl.arm_view).
    arm = arm_view(mapping, T_capture, services.config)
    matches = [r for r in found.matches if arm is None or not arm.covers(r.u_px, r.v_px)]
    cands = [candidate(mapping, recipe, r, T_capture, near, robot) for r in matches[: recipe.search.max_count]]
    picks = [c.as_json() for c in cands]
    reason = found.reason()
    T_fixture, fixture_found = None, None
    if fixture is not None:
        T_fixture, fixture_found = locate_fixture(fixture, frame.pixels, mapping,
                                                  T_capture if mapping.kind == "handeye" else None)
    frame_id = services.frames.add(frame.pixels, picks, match_contours(models, picks), reason)
    t_done = time.perf_counter()
    services.metrics.observe_pick(t_done - t0, [c.match.score for c in cands])
    return Located(recipe_id, version, cam_id, robot.robot_id, mapping, T_capture, cands, frame_id, reason,
                   found.timed_out, [x.as_dict() for x in found.rejected],
                   {"grab": (t_grab - t0) * 1e3, "find": (t_find - t_grab) * 1e3, "total": (t_done - t0) * 1e3},
                   {"kind": mapping.kind, "id": mapping.calibration_id}, arm, recipe.search.roi,
                   _arm_in(arm, recipe.search.roi), _ticks(frame.metadata.get("encoder_ticks")), T_fixture,
                   fixture_found)
