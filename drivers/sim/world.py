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
"""

from __future__ import annotations

import functools
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
from drivers.sim.imaging import Imaging, PlanarObject, render_scene, to_grey
from drivers.sim.kinematics import KinematicError
from drivers.sim.outline import part_mask
from drivers.sim.production import ProductionParts
from drivers.sim.production_view import production_objects, production_truth
from drivers.sim.scene import PartSpec, SceneError, SceneSpec, load_scene, resolve_scene

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
        self._reflectance_cache: tuple[bytes, NDArray[np.float64], NDArray[np.float64]] | None = None
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
                    return self._on_belt(T)
                return self.T_base_tool_true @ T if spec.attached_to == "tool" else T
        raise KeyError(f"no target named {name!r} in the scene")

    def _on_belt(self, T: NDArray[np.float64], s_m: float | None = None) -> NDArray[np.float64]:
        if self.belt is None:
            raise SceneError("a target attached_to: belt needs the scene's conveyor")
        return self.belt.carried(T, s_m)

    def planar_objects(self, s_m: float | None = None) -> list[PlanarObject]:
        """Everything visible, as planes in the camera frame: targets, then the parts, the table.

        The parts lie in the table's own frame, so they tie with it in depth and win (the renderer
        gives a tie to the object listed first; where parts overlap, the scene's last part wins,
        as it is listed first here). Each part is bounded by its outline's circle, so only the
        pixels near it are tested against it.
        """
        T_cam_base = g.invert(self.T_base_cam())
        objs = [PlanarObject(T_cam_base @ (self._on_belt(g.ur_pose_to_transform(spec.pose), s_m)
                                           if spec.attached_to == "belt" else self.T_base_target(spec.name)),
                             target.reflectance) for spec, target in self._targets]
        table = self.scene.table
        T_cam_table = T_cam_base @ g.make_transform(np.eye(3), [0.0, 0.0, table.z_m])
        for mark in self.scene.fiducials:
            # A mark on the table lies in the table's own frame (it ties with it in depth and, listed
            # first, wins); one above it in its own level plane.
            r_m, x_m, y_m = mark.diameter_mm / 2000.0, mark.x_mm / 1000.0, mark.y_mm / 1000.0
            dz = mark.z_mm / 1000.0 - table.z_m
            T_plane = T_cam_table if abs(dz) < 1e-9 else T_cam_table @ g.make_transform(np.eye(3), [0.0, 0.0, dz])
            objs.append(PlanarObject(T_plane, functools.partial(_disk, x_m, y_m, r_m, mark.reflectance),
                                     (x_m - r_m, y_m - r_m, x_m + r_m, y_m + r_m)))
        if self.production is not None:
            objs.extend(production_objects(self.production, T_cam_base, self.T_base_tool_true, s_m))
        for part in reversed(self.scene.parts):
            r_m = float(np.max(np.linalg.norm(np.asarray(part.outline_mm, dtype=np.float64), axis=1))) / 1000.0
            x_m, y_m = part.x_mm / 1000.0, part.y_mm / 1000.0
            objs.append(PlanarObject(T_cam_table, functools.partial(self._part_reflectance, part),
                                     (x_m - r_m, y_m - r_m, x_m + r_m, y_m + r_m)))
        objs.append(PlanarObject(T_cam_table, self._table_reflectance))
        return objs

    def render(self) -> NDArray[np.uint8]:
        """A grey image of what the camera sees now (``render_with_meta``'s pixels)."""
        return self.render_with_meta()[0]

    def render_with_meta(self) -> tuple[NDArray[np.uint8], dict[str, Any]]:
        """A grey image of what the camera sees now (noise drawn from the world's generator), and what the
        frame carries: with a belt, ``encoder_ticks`` latched at the exposure (the belt frozen there).

        The geometric rendering (the expensive part) is cached for as long as the camera's pose
        and the scene's parts stay put; every frame still gets its own lighting, blur, noise and
        the other imaging defects of the scene (``drivers.sim.imaging.sensor``).
        """
        im = self.scene.camera.imaging
        imaging = Imaging(**im.model_dump(exclude={"supersample"}))
        meta: dict[str, Any] = {}
        s_m = None
        if self.belt is not None:
            t_exposure = time.monotonic()
            s_m = self.belt.position_m(t_exposure)
            meta["encoder_ticks"] = self.belt.latched_ticks(t_exposure)
        with self._lock:
            key = self.T_base_cam().tobytes() + repr([p.model_dump() for p in self.scene.parts]).encode()
            if s_m is not None:
                key += b"belt%.7f" % s_m
            if self.production is not None:
                key += self.production.key(self.T_base_tool_true, s_m)
            if any(spec.attached_to == "tool" for spec, _ in self._targets):
                key += self.T_base_tool_true.tobytes()  # a target on the tool moves with it
            cached = self._reflectance_cache
            hit = cached is not None and cached[0] == key
            objects = [] if hit else self.planar_objects(s_m)
            self.frame_counter += 1
            rng = np.random.default_rng(self._rng.integers(2**63))
        if hit and cached is not None:
            reflectance, depth_m = cached[1], cached[2]
        else:
            reflectance, depth_m = render_scene(self.camera_model, objects, im.background, im.supersample)
            with self._lock:
                self._reflectance_cache = (key, reflectance, depth_m)
        return to_grey(reflectance, imaging, rng, depth_m), meta

    def _table_reflectance(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        table = self.scene.table
        out = np.full(x.shape, table.reflectance)
        sx, sy = table.size_m
        out[(np.abs(x) > sx / 2) | (np.abs(y) > sy / 2)] = np.nan
        return out

    def _part_reflectance(self, part: PartSpec, x: NDArray[np.float64], y: NDArray[np.float64]
                          ) -> NDArray[np.float64]:
        """The part where it lies (and the table is), NaN elsewhere (table frame, metres)."""
        sx, sy = self.scene.table.size_m
        inside = part_mask(part.outline_mm, part.holes_mm, part.x_mm, part.y_mm, part.angle_deg, x, y)
        inside &= (np.abs(x) <= sx / 2) & (np.abs(y) <= sy / 2)
        out = np.full(x.shape, np.nan)
        out[inside] = part.reflectance
        return out

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


def _disk(x0_m: float, y0_m: float, r_m: float, reflectance: float, x: NDArray[np.float64],
          y: NDArray[np.float64]) -> NDArray[np.float64]:
    """A fiducial mark: ``reflectance`` inside its disk, NaN elsewhere (table frame, metres)."""
    dx, dy = x - x0_m, y - y0_m
    return np.where(dx * dx + dy * dy <= r_m * r_m, reflectance, np.nan)


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
