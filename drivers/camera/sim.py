"""Simulated camera (``kind: sim``): renders the virtual cell from the camera's true pose."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration import geometry as g
from drivers.base import CameraBase, DeviceInitError, DeviceUnavailable, Frame
from drivers.sim.imaging import prepare
from drivers.sim.tool_feature import draw_tool_feature
from drivers.sim.world import SimWorld, world_for

PREPARE_JOIN_S = 120.0
"""close() waits this long for the open's preparation (a cold numba cache compiles the renderer's loops)."""


class SimCameraSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene: str | None = None
    """Scene file path; empty for the built-in virtual cell."""
    seed: int | None = Field(None, ge=0)
    exposure_us: float = Field(10000.0, gt=0, le=10_000_000)
    gain_db: float = Field(0.0, ge=0, le=48)


class SimCamera(CameraBase):
    """A camera that renders the virtual cell's scene as seen from its (possibly moving) mount.

    A scene's ``tool_feature`` (a bright disk on the tool) is drawn over each frame where the
    camera sees it, from the tool's true pose at the time of the grab (``drivers.sim.tool_feature``).
    """

    Settings = SimCameraSettings

    def __init__(self, camera_id: str, settings: SimCameraSettings) -> None:
        super().__init__(camera_id)
        self._settings = settings
        self._world: SimWorld | None = None
        self._frame_id = 0
        self._exposure_us = settings.exposure_us
        self._gain_db = settings.gain_db
        self._trigger = "software"
        self._feature_rng = np.random.default_rng()
        self._prepare: threading.Thread | None = None

    @property
    def world(self) -> SimWorld:
        if self._world is None:
            raise DeviceUnavailable(f"camera {self.camera_id}: not open; open() it first")
        return self._world

    def open(self) -> None:
        self._world = world_for(self._settings.scene, self._settings.seed)
        self._feature_rng = np.random.default_rng([self._world.scene.seed, 0x70_0F])
        # The first frame's one-off work (lens inversion, loading the renderer's compiled loops)
        # starts now, so that a grab soon after open does not pay it all; a grab meanwhile waits.
        # The thread is bounded (one lens inversion and one load) and joined by close().
        self._prepare = threading.Thread(target=prepare, args=(self._world.camera_model,),
                                         name=f"{self.camera_id}-prepare", daemon=True)
        self._prepare.start()

    def warm_up(self) -> None:
        """Do the first frame's one-off work now and return when it is done: invert the lens and
        load the renderer's compiled loops (compiling them on a cold numba cache). Thread-safe, and
        cheap once done; it renders no frame, so the seeded scene's frames stay as they were.
        A service calls it before it counts a grab's time against a deadline."""
        prepare(self.world.camera_model)

    def close(self) -> None:
        self._world = None
        thread, self._prepare = self._prepare, None
        if thread is not None:
            thread.join(PREPARE_JOIN_S)

    def grab(self, timeout_s: float = 2.0) -> Frame:
        world = self.world
        T_base_tool = world.T_base_tool_true
        pixels, exposure = world.render_with_meta()  # a belt's encoder count latched at the exposure
        feature = world.scene.tool_feature
        if feature is not None:
            T_cam_tool = g.invert(world.T_base_cam()) @ T_base_tool
            pixels = draw_tool_feature(pixels, world.camera_model, T_cam_tool, feature, world.scene.camera.imaging,
                                       self._feature_rng)
        self._frame_id += 1
        # Exposure and gain scale the light the configured settings rendered (clipped at full scale).
        scale = (self._exposure_us / self._settings.exposure_us) * 10.0 ** (
            (self._gain_db - self._settings.gain_db) / 20.0)
        if scale != 1.0:
            pixels = np.clip(pixels.astype(np.float32) * scale, 0, 255).astype(np.uint8)
        return Frame(
            pixels=pixels,
            timestamp_s=time.time(),
            frame_id=self._frame_id,
            camera_id=self.camera_id,
            metadata={"exposure_us": self._exposure_us, "gain_db": self._gain_db, "simulated": True, **exposure},
        )

    def set_exposure_us(self, exposure_us: float) -> None:
        self._exposure_us = float(exposure_us)

    def set_gain_db(self, gain_db: float) -> None:
        self._gain_db = float(gain_db)

    def set_trigger(self, mode: str) -> None:
        if mode not in ("software", "free_run"):
            raise DeviceInitError(f"camera {self.camera_id}: trigger mode {mode!r} unknown; use software or free_run")
        self._trigger = mode

    def control_ranges(self) -> dict[str, Any]:
        """Exposure (us) and gain (dB) within the settings' bounds (they scale the rendered light), the
        trigger modes it takes."""
        return {"exposure_us": [1.0, 10_000_000.0], "gain_db": [0.0, 48.0], "trigger": ["software", "free_run"]}

    def settings(self) -> dict[str, Any]:
        model = self._world.camera_model if self._world else None
        return {
            "kind": "sim",
            "exposure_us": self._exposure_us,
            "gain_db": self._gain_db,
            "trigger": self._trigger,
            "width": model.width if model else None,
            "height": model.height if model else None,
        }
