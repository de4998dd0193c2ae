"""The virtual cell's shared world: where the robot really is, and what the camera sees.

One ``SimWorld`` per scene is shared by the simulated camera and robot of a cell (looked up by
scene path and seed), so that an eye-in-hand camera renders from the robot's true pose. The
robot *reports* its pose with repeatability noise drawn once per move; the camera renders from
the true pose — as on a real cell, where the encoders' pose and the physical pose differ.

A production scene's world keeps its state in a file when told where (``keep_state_in``, by the sim
robot's ``state_file``): the parts (where they lie, which one the gripper holds), the gripper and
the arm's pose are written whenever a part moves, a move ends or a halted arm stands, and read back
when a service starts on the same file — as a real cell's parts and arm stay where they are when
its controller restarts.

A conveyor scene's world has a belt (``belt``, ``drivers.sim.conveyor``): its parts ride it, a target
``attached_to: belt`` too, and the robot can track it (``start_tracking``: as a robot controller with
the belt's encoder wired to it does, every commanded pose is then carried along the belt by the
travel the encoder counted since, so the tool follows the belt). Its state is not kept across a
restart (the belt moved on meanwhile).

What the camera sees, the cell's planes and the frames rendered from them, is ``drivers.sim.world_view``'s
(``SimWorld.view``).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from drivers.sim.camera_fault import CameraFault
from drivers.sim.conveyor import BeltTracker, SimBelt
from drivers.sim.imaging import PlanarObject
from drivers.sim.kinematics import KinematicError
from drivers.sim.outline import part_mask
from drivers.sim.production import ProductionParts
from drivers.sim.production_view import production_truth
from drivers.sim.scene import SceneError, SceneSpec, load_scene, resolve_scene
from drivers.sim.world_view import CameraView, on_belt

log = logging.getLogger(__name__)
__all__ = ["SimWorld", "forget_worlds", "part_mask", "world_for"]

KEEP_MOVING_EVERY_S = 0.05
"""While the arm moves, its pose is written to the state file at most this often."""


class SimWorld:
    """Ground truth and state of one virtual cell."""

    def __init__(self, scene: SceneSpec, source: str = "built-in") -> None:
        self.scene = scene
        self.source = source
        self.camera_model = scene.camera.camera_model()
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(scene.seed)
        ke = scene.robot.kinematic_error
        self._kinematics = (None if ke is None else
                            KinematicError(ke.seed, ke.link_sigma_mm, ke.joint_offset_sigma_deg))
        self._T_base_tool_cmd = g.ur_pose_to_transform(scene.robot.home)
        self._joints_rad, self._T_base_tool_true = self.true_pose_for(self._T_base_tool_cmd)
        self._T_report_error = np.eye(4)
        self.frame_counter = 0
        self._targets = [(t, t.parsed()) for t in scene.targets]
        self.belt = None if scene.conveyor is None else SimBelt(scene.conveyor, scene.seed)
        """The conveyor's belt and encoder; None without one."""
        self.tracker = BeltTracker(self.belt, self._lock)
        prod = scene.production
        self.production = None if prod is None else ProductionParts(prod, scene.table.z_m, scene.seed, self.belt)
        """The production scene's parts (picked and placed by a sim gripper); None without one."""
        self._state_file: Path | None = None
        self._kept_s = 0.0
        self.tool_source: Callable[[], NDArray[np.float64]] | None = None
        """An arm outside the virtual cell its tool follows (its true pose is what that arm says now; the tests'
        UR emulator, ``tests/support/ur_conveyor.py``); None: the sim robot moves the tool."""
        self.camera_fault = CameraFault()
        """A bump of the camera on request (``POST /sim/faults``): applied to its true pose."""
        self.view = CameraView(self, self._lock, self._rng, self._targets)
        """What the camera sees: the cell's planes and the frames rendered from them (``drivers.sim.world_view``)."""

    # -- robot ------------------------------------------------------------------------------------
    @property
    def T_base_tool_true(self) -> NDArray[np.float64]:
        source = self.tool_source
        if source is not None:
            return source()
        with self._lock:
            return self.tracker.shifted(self._T_base_tool_true)

    @property
    def T_base_tool_commanded(self) -> NDArray[np.float64]:
        """Where the controller believes the tool is (the last commanded or interpolated pose; while it
        tracks the belt, in the frame of its commands: the belt where tracking started)."""
        with self._lock:
            return self._T_base_tool_cmd.copy()

    def raw_true_pose(self) -> NDArray[np.float64]:
        """The true pose in the frame of the commands (without the belt's travel while tracking)."""
        with self._lock:
            return self._T_base_tool_true.copy()

    def settle_tracking(self) -> None:
        """Before a move or tracking starts (no move under way): the travel the tool followed is taken into
        its poses, whose frame is the base's again (``BeltTracker.settle``)."""
        with self._lock:
            shift = self.tracker.settle()
            self._T_base_tool_cmd = self._T_base_tool_cmd.copy()
            self._T_base_tool_true = self._T_base_tool_true.copy()
            self._T_base_tool_cmd[:3, 3] += shift
            self._T_base_tool_true[:3, 3] += shift

    @property
    def joints_rad(self) -> NDArray[np.float64]:
        with self._lock:
            return self._joints_rad.copy()

    def T_base_tool_reported(self) -> NDArray[np.float64]:
        """The pose the robot controller reports: its belief with its repeatability error.

        Without a kinematic error model the belief is the true pose; with one, the true pose is
        the perturbed arm's (``true_pose_for``) while the report stays near the commanded pose.
        """
        with self._lock:
            return self.tracker.shifted(self._T_base_tool_cmd) @ self._T_report_error

    def true_pose_for(self, T_base_tool_commanded: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                                 NDArray[np.float64]]:
        """(joints, true pose) of the arm when its controller is at ``T_base_tool_commanded``.

        Raises ``OutOfReach`` (a ValueError) when the kinematic model has no solution.
        """
        T = np.asarray(T_base_tool_commanded, dtype=np.float64)
        if self._kinematics is None:
            return np.zeros(6), T.copy()
        with self._lock:
            return self._kinematics.solve(T)

    def set_moving_pose(self, T_commanded: NDArray[np.float64], T_true: NDArray[np.float64]) -> None:
        """The tool is on its way: believed and true pose of this instant (no fresh noise)."""
        with self._lock:
            self._T_base_tool_cmd = np.asarray(T_commanded, dtype=np.float64).copy()
            self._T_base_tool_true = np.asarray(T_true, dtype=np.float64).copy()
        if self._state_file is not None and time.monotonic() - self._kept_s >= KEEP_MOVING_EVERY_S:
            self.keep()

    def place_tool(self, T_base_tool_commanded: NDArray[np.float64],
                   T_true: NDArray[np.float64] | None = None, joints_rad: NDArray[np.float64] | None = None) -> None:
        """Complete a move: the tool settles at the commanded pose, reported with fresh noise."""
        spec = self.scene.robot
        if T_true is None:
            joints, T_true = self.true_pose_for(T_base_tool_commanded)
            joints_rad = joints if joints_rad is None else joints_rad
        with self._lock:
            self._T_base_tool_cmd = np.asarray(T_base_tool_commanded, dtype=np.float64).copy()
            self._T_base_tool_true = np.asarray(T_true, dtype=np.float64).copy()
            if joints_rad is not None:
                self._joints_rad = np.asarray(joints_rad, dtype=np.float64).copy()
            dt = self._rng.normal(0.0, spec.repeatability_mm * 1e-3, 3)
            axis = self._rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            angle = self._rng.normal(0.0, np.radians(spec.repeatability_deg))
            self._T_report_error = g.make_transform(g.rotvec_to_matrix(axis * angle), dt)
        self.keep()

    def move_started(self, speed_m_s: float) -> None:
        """The robot starts a move at ``speed_m_s``: a held part may slip (``production.gripper.slip_accel_m_s2``)."""
        if self.production is not None:
            self.production.move_started(speed_m_s, self.T_base_tool_true)
            self.keep()

    # -- state kept across a restart ----------------------------------------------------------------
    def keep_state_in(self, path: str | Path) -> None:
        """Keep this production world's state in ``path``: read it back now when it is there (the same
        scene's), then write it on every change. Nothing for a scene without production; a second call
        (another device of the same world) changes nothing."""
        if self.production is None or self._state_file is not None or self.belt is not None:
            return
        path = Path(path)
        try:
            kept = json.loads(path.read_text())
        except FileNotFoundError:
            kept = None
        except (OSError, ValueError) as exc:
            log.warning("sim: the kept state %s cannot be read (%s); the scene starts afresh", path, exc)
            kept = None
        if kept is not None:
            try:
                if kept.get("scene") != self.scene.name or kept.get("seed") != self.scene.seed:
                    raise ValueError(f"it is scene {kept.get('scene')!r} seed {kept.get('seed')}")
                self.production.set_state(kept["production"])
                with self._lock:
                    self._T_base_tool_cmd = np.asarray(kept["T_base_tool_commanded"], dtype=np.float64)
                    self._T_base_tool_true = np.asarray(kept["T_base_tool_true"], dtype=np.float64)
                    self._joints_rad = np.asarray(kept["joints_rad"], dtype=np.float64)
            except (KeyError, TypeError, ValueError) as exc:
                log.warning("sim: the kept state %s is not this scene's (%s); the scene starts afresh", path, exc)
        self._state_file = path
        self.keep()

    def keep(self) -> None:
        """Write the state file now (atomically: a kill leaves the old or the new one)."""
        path = self._state_file
        if path is None or self.production is None:
            return
        with self._lock:
            self._kept_s = time.monotonic()
            state = {"scene": self.scene.name, "seed": self.scene.seed, "production": self.production.state(),
                     "T_base_tool_commanded": self._T_base_tool_cmd.tolist(),
                     "T_base_tool_true": self._T_base_tool_true.tolist(), "joints_rad": self._joints_rad.tolist()}
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_name(f".{path.name}.tmp")
                tmp.write_text(json.dumps(state))
                os.replace(tmp, path)
            except OSError as exc:
                log.warning("sim: the state cannot be kept in %s: %s", path, exc)

    # -- camera -----------------------------------------------------------------------------------
    def T_base_cam(self) -> NDArray[np.float64]:
        """The camera's true pose (with the fault in force, ``camera_fault``)."""
        fixed = self.scene.T_base_cam_fixed()
        if fixed is not None:
            return self.camera_fault.apply(fixed)
        T_tool_cam = self.scene.T_tool_cam()
        if T_tool_cam is None:
            raise SceneError("the scene's camera has neither T_base_cam (mount: base) nor T_tool_cam (mount: tool)")
        return self.camera_fault.apply(self.T_base_tool_true @ T_tool_cam)

    def T_base_target(self, name: str) -> NDArray[np.float64]:
        for spec, _ in self._targets:
            if spec.name == name:
                T = g.ur_pose_to_transform(spec.pose)
                if spec.attached_to == "belt":
                    return on_belt(self.belt, T)
                return self.T_base_tool_true @ T if spec.attached_to == "tool" else T
        raise KeyError(f"no target named {name!r} in the scene")

    def planar_objects(self, s_m: float | None = None) -> list[PlanarObject]:
        """Everything visible, as planes in the camera frame (``world_view.CameraView.planar_objects``)."""
        return self.view.planar_objects(s_m)

    def render(self) -> NDArray[np.uint8]:
        """A grey image of what the camera sees now (``render_with_meta``'s pixels)."""
        return self.render_with_meta()[0]

    def render_with_meta(self) -> tuple[NDArray[np.uint8], dict[str, Any]]:
        """A grey image of what the camera sees now and what the frame carries (with a belt, ``encoder_ticks``
        latched at the exposure): ``world_view.CameraView.render_with_meta``."""
        return self.view.render_with_meta()

    # -- truth ------------------------------------------------------------------------------------
    def truth(self) -> dict[str, Any]:
        """Ground truth as plain JSON-able values (metres, radians; mm where named)."""
        cam = self.scene.camera
        out: dict[str, Any] = {
            "scene": self.scene.name,
            "source": self.source,
            "camera": self.camera_model.to_dict(),
            "mount": cam.mount,
            "T_base_tool": self.T_base_tool_true.tolist(),
            "T_base_tool_reported": self.T_base_tool_reported().tolist(),
            "T_base_cam": self.T_base_cam().tolist(),
            "targets": {
                spec.name: {
                    "target": spec.target,
                    "attached_to": spec.attached_to,
                    "T_base_target": self.T_base_target(spec.name).tolist(),
                    **({"T_tool_target": g.ur_pose_to_transform(spec.pose).tolist()}
                       if spec.attached_to == "tool" else {}),
                }
                for spec, _ in self._targets
            },
            "parts": [
                {"name": p.name, "x_mm": p.x_mm, "y_mm": p.y_mm, "angle_deg": p.angle_deg,
                 "z_mm": self.scene.table.z_m * 1000.0}
                for p in self.scene.parts
            ],
            "fiducials": [m.model_dump() for m in self.scene.fiducials],
            "camera_fault": self.camera_fault.state(),
            "robot_repeatability": {"mm": self.scene.robot.repeatability_mm,
                                    "deg": self.scene.robot.repeatability_deg},
            "timestamp_s": time.time(),
        }
        T_tool_cam = self.scene.T_tool_cam()
        if T_tool_cam is not None:
            out["T_tool_cam"] = T_tool_cam.tolist()
        else:
            out["camera"] = {**out["camera"], "T_base_cam": out["T_base_cam"]}
        if self.belt is not None:
            out["conveyor"] = {**self.belt.truth(), "tracking": self.tracker.tracking}
        if self.production is not None:
            # A production scene's parts are objects with a state (INTERFACES: /sim/truth).
            out.update(production_truth(self.production, self.camera_model, self.T_base_cam(),
                                        self.T_base_tool_true))
        feature = self.scene.tool_feature
        if feature is not None:  # the tool centre's truth: the feature's offset from the flange, mm
            T_tool_feature = g.make_transform(np.eye(3), np.asarray(feature.offset_mm) * 1e-3)
            out["tool_feature"] = {**feature.model_dump(mode="json"),
                                   "T_base_feature": (self.T_base_tool_true @ T_tool_feature).tolist()}
        return out


_WORLDS: dict[tuple[str, int], SimWorld] = {}
_WORLDS_LOCK = threading.Lock()


def world_for(scene_path: str | Path | None, seed: int | None = None) -> SimWorld:
    """The shared world of a scene file (built-in when ``None``), created on first use."""
    scene_path = resolve_scene(scene_path)
    key = (str(Path(scene_path).resolve()) if scene_path else "built-in", -1 if seed is None else seed)
    with _WORLDS_LOCK:
        world = _WORLDS.get(key)
        if world is None:
            scene = load_scene(scene_path)
            if seed is not None:
                scene = scene.model_copy(update={"seed": seed})
            world = SimWorld(scene, key[0])
            _WORLDS[key] = world
        return world


def forget_worlds(scene_path: str | Path | None = None, *, only_that_scene: bool = False) -> None:
    """Drop the shared worlds (a fresh start, e.g. when a service restarts in-process): all of them, or
    (``only_that_scene``) those of one scene file (the built-in scene when ``scene_path`` is None)."""
    with _WORLDS_LOCK:
        if not only_that_scene:
            _WORLDS.clear()
            return
        resolved = resolve_scene(scene_path)
        name = str(Path(resolved).resolve()) if resolved else "built-in"
        for key in [k for k in _WORLDS if k[0] == name]:
            del _WORLDS[key]
