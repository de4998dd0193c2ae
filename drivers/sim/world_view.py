"""What the virtual cell's camera sees (``drivers.sim.world.SimWorld``'s view): the cell as planes in
the camera frame, and the frames rendered from them.

The planes are the targets, the fiducial marks, a production scene's parts, the scene's parts and the
table, in that order (the renderer gives a depth tie to the plane listed first). The geometric render
(the expensive part) is cached for as long as the camera's pose and the parts stay put; every frame
still gets its own lighting, blur, noise and the other imaging defects (``drivers.sim.imaging.sensor``).
Units: metres in the table's and the base's frames, grey levels (DN, 0..255) in the frames.
"""

from __future__ import annotations

import functools
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from drivers.sim.conveyor import SimBelt
from drivers.sim.imaging import Imaging, PlanarObject, render_scene, to_grey
from drivers.sim.outline import part_mask
from drivers.sim.production_view import production_objects
from drivers.sim.scene import PartSpec, SceneError, TargetSpec

if TYPE_CHECKING:
    from drivers.sim.world import SimWorld


def on_belt(belt: SimBelt | None, T: NDArray[np.float64], s_m: float | None = None) -> NDArray[np.float64]:
    """A pose ``attached_to: belt`` carried by the belt's travel (``SimBelt.carried``; ``s_m``: the belt's
    position, metres, None: now)."""
    if belt is None:
        raise SceneError("a target attached_to: belt needs the scene's conveyor")
    return belt.carried(T, s_m)


class CameraView:
    """The planes and frames of one world's camera. ``lock``, ``rng`` and ``targets`` are the world's
    own (its lock, the generator every frame's noise is drawn from, its targets with their parsed form)."""

    def __init__(self, world: SimWorld, lock: threading.RLock, rng: np.random.Generator,
                 targets: list[tuple[TargetSpec, Any]]) -> None:
        self._world = world
        self._lock = lock
        self._rng = rng
        self._targets = targets
        self._reflectance_cache: tuple[bytes, NDArray[np.float64], NDArray[np.float64]] | None = None

    def planar_objects(self, s_m: float | None = None) -> list[PlanarObject]:
        """Everything visible, as planes in the camera frame: targets, then the parts, the table.

        The parts lie in the table's own frame, so they tie with it in depth and win (the renderer
        gives a tie to the object listed first; where parts overlap, the scene's last part wins,
        as it is listed first here). Each part is bounded by its outline's circle, so only the
        pixels near it are tested against it.
        """
        world = self._world
        T_cam_base = g.invert(world.T_base_cam())
        objs = [PlanarObject(T_cam_base @ (on_belt(world.belt, g.ur_pose_to_transform(spec.pose), s_m)
                                           if spec.attached_to == "belt" else world.T_base_target(spec.name)),
                             target.reflectance) for spec, target in self._targets]
        table = world.scene.table
        T_cam_table = T_cam_base @ g.make_transform(np.eye(3), [0.0, 0.0, table.z_m])
        for mark in world.scene.fiducials:
            # A mark on the table lies in the table's own frame (it ties with it in depth and, listed
            # first, wins); one above it in its own level plane.
            r_m, x_m, y_m = mark.diameter_mm / 2000.0, mark.x_mm / 1000.0, mark.y_mm / 1000.0
            dz = mark.z_mm / 1000.0 - table.z_m
            T_plane = T_cam_table if abs(dz) < 1e-9 else T_cam_table @ g.make_transform(np.eye(3), [0.0, 0.0, dz])
            objs.append(PlanarObject(T_plane, functools.partial(_disk, x_m, y_m, r_m, mark.reflectance),
                                     (x_m - r_m, y_m - r_m, x_m + r_m, y_m + r_m)))
        if world.production is not None:
            objs.extend(production_objects(world.production, T_cam_base, world.T_base_tool_true, s_m))
        for part in reversed(world.scene.parts):
            r_m = float(np.max(np.linalg.norm(np.asarray(part.outline_mm, dtype=np.float64), axis=1))) / 1000.0
            x_m, y_m = part.x_mm / 1000.0, part.y_mm / 1000.0
            objs.append(PlanarObject(T_cam_table, functools.partial(self._part_reflectance, part),
                                     (x_m - r_m, y_m - r_m, x_m + r_m, y_m + r_m)))
        objs.append(PlanarObject(T_cam_table, self._table_reflectance))
        return objs

    def render_with_meta(self) -> tuple[NDArray[np.uint8], dict[str, Any]]:
        """A grey image of what the camera sees now (noise drawn from the world's generator), and what the
        frame carries: with a belt, ``encoder_ticks`` latched at the exposure (the belt frozen there).
        Counts the world's ``frame_counter`` up."""
        world = self._world
        im = world.scene.camera.imaging
        imaging = Imaging(**im.model_dump(exclude={"supersample"}))
        meta: dict[str, Any] = {}
        s_m = None
        if world.belt is not None:
            t_exposure = time.monotonic()
            s_m = world.belt.position_m(t_exposure)
            meta["encoder_ticks"] = world.belt.latched_ticks(t_exposure)
        with self._lock:
            key = world.T_base_cam().tobytes() + repr([p.model_dump() for p in world.scene.parts]).encode()
            if s_m is not None:
                key += b"belt%.7f" % s_m
            if world.production is not None:
                key += world.production.key(world.T_base_tool_true, s_m)
            if any(spec.attached_to == "tool" for spec, _ in self._targets):
                key += world.T_base_tool_true.tobytes()  # a target on the tool moves with it
            cached = self._reflectance_cache
            hit = cached is not None and cached[0] == key
            objects = [] if hit else self.planar_objects(s_m)
            world.frame_counter += 1
            rng = np.random.default_rng(self._rng.integers(2**63))
        if hit and cached is not None:
            reflectance, depth_m = cached[1], cached[2]
        else:
            reflectance, depth_m = render_scene(world.camera_model, objects, im.background, im.supersample)
            with self._lock:
                self._reflectance_cache = (key, reflectance, depth_m)
        return to_grey(reflectance, imaging, rng, depth_m), meta

    def _table_reflectance(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        table = self._world.scene.table
        out = np.full(x.shape, table.reflectance)
        sx, sy = table.size_m
        out[(np.abs(x) > sx / 2) | (np.abs(y) > sy / 2)] = np.nan
        return out

    def _part_reflectance(self, part: PartSpec, x: NDArray[np.float64], y: NDArray[np.float64]
                          ) -> NDArray[np.float64]:
        """The part where it lies (and the table is), NaN elsewhere (table frame, metres)."""
        sx, sy = self._world.scene.table.size_m
        inside = part_mask(part.outline_mm, part.holes_mm, part.x_mm, part.y_mm, part.angle_deg, x, y)
        inside &= (np.abs(x) <= sx / 2) & (np.abs(y) <= sy / 2)
        out = np.full(x.shape, np.nan)
        out[inside] = part.reflectance
        return out


def _disk(x0_m: float, y0_m: float, r_m: float, reflectance: float, x: NDArray[np.float64],
          y: NDArray[np.float64]) -> NDArray[np.float64]:
    """A fiducial mark: ``reflectance`` inside its disk, NaN elsewhere (table frame, metres)."""
    dx, dy = x - x0_m, y - y0_m
    return np.where(dx * dx + dy * dy <= r_m * r_m, reflectance, np.nan)
