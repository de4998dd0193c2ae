"""Replay adapters (``kind: replay``): play a ``cellctl record`` folder back as a camera and a robot.

``speed`` 1.0 plays at the recorded timing (a frame is returned when its recorded time since
the first frame has elapsed), 2.0 twice as fast, 0 as fast as asked (each call returns the next
item). At the end the playback stops with ``DeviceUnavailable`` or, with ``loop: true``, restarts.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from drivers.base import (
    CameraBase,
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    Frame,
    MotionLimits,
    MotionRejected,
    RobotBase,
    RobotState,
)
from drivers.health import DeviceHealth
from drivers.recording import Recording, RecordingError


class ReplaySettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str
    """The recording folder."""
    source_id: str | None = None
    """Which recorded camera/robot to play; default the first one."""
    speed: float = Field(0.0, ge=0, le=1000)
    loop: bool = False


class _Clock:
    """Maps recorded timestamps to playback time."""

    def __init__(self, speed: float, first_s: float) -> None:
        self.speed = speed
        self.first_s = first_s
        self.start = time.monotonic()

    def wait_until(self, recorded_s: float, timeout_s: float) -> bool:
        if self.speed <= 0:
            return True
        due = self.start + (recorded_s - self.first_s) / self.speed
        delay = due - time.monotonic()
        if delay > timeout_s:
            return False
        if delay > 0:
            time.sleep(delay)
        return True

    def elapsed_recorded_s(self) -> float:
        return self.first_s + (time.monotonic() - self.start) * self.speed


class ReplayCamera(CameraBase):
    """A camera that plays back recorded frames."""

    Settings = ReplaySettings

    def __init__(self, camera_id: str, settings: ReplaySettings) -> None:
        super().__init__(camera_id)
        self._settings = settings
        self._frames: list[Any] = []
        self._index = 0
        self._clock: _Clock | None = None

    def open(self) -> None:
        try:
            self._frames = Recording(self._settings.path).camera_frames(self._settings.source_id)
        except RecordingError as exc:
            raise DeviceUnavailable(f"camera {self.camera_id}: {exc}") from exc
        self._index = 0
        self._clock = _Clock(self._settings.speed, self._frames[0].timestamp_s)

    def close(self) -> None:
        self._clock = None

    def health(self) -> DeviceHealth:
        if self._clock is None:
            return DeviceHealth(available=False, reason="not open")
        if self._index >= len(self._frames) and not self._settings.loop:
            return DeviceHealth(available=False, reason="the recording has ended")
        return DeviceHealth(available=True)

    def grab(self, timeout_s: float = 2.0) -> Frame:
        if self._clock is None:
            raise DeviceUnavailable(f"camera {self.camera_id}: not open")
        if self._index >= len(self._frames):
            if not self._settings.loop:
                raise DeviceUnavailable(f"camera {self.camera_id}: the recording has ended "
                                        f"({len(self._frames)} frames); set loop: true to repeat it")
            self._index = 0
            self._clock = _Clock(self._settings.speed, self._frames[0].timestamp_s)
        entry = self._frames[self._index]
        if not self._clock.wait_until(entry.timestamp_s, timeout_s):
            raise DeviceTimeout(f"camera {self.camera_id}: next recorded frame is not due within {timeout_s} s")
        pixels = cv2.imread(str(entry.file), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise DeviceOperationError(f"camera {self.camera_id}: recorded frame {entry.file} is unreadable")
        self._index += 1
        return Frame(pixels=pixels, timestamp_s=entry.timestamp_s, frame_id=entry.frame_id,
                     camera_id=self.camera_id, metadata={"replay": str(entry.file)})

    def settings(self) -> dict[str, Any]:
        return {"kind": "replay", "path": self._settings.path, "speed": self._settings.speed,
                "frames": len(self._frames), "position": self._index}


class ReplayRobot(RobotBase):
    """A robot whose state is played back; it refuses every motion (there is nothing to move)."""

    Settings = ReplaySettings

    def __init__(self, robot_id: str, settings: ReplaySettings, limits: MotionLimits) -> None:
        super().__init__(robot_id, limits)
        self._settings = settings
        self._states: list[RobotState] = []
        self._index = 0
        self._clock: _Clock | None = None

    def connect(self) -> None:
        try:
            self._states = Recording(self._settings.path).robot_states(self._settings.source_id)
        except RecordingError as exc:
            raise DeviceUnavailable(f"robot {self.robot_id}: {exc}") from exc
        self._index = 0
        self._clock = _Clock(self._settings.speed, self._states[0].timestamp_s)

    def close(self) -> None:
        self._clock = None

    def health(self) -> DeviceHealth:
        if self._clock is None:
            return DeviceHealth(available=False, reason="not connected")
        return DeviceHealth(available=True)

    def state(self) -> RobotState:
        if self._clock is None:
            raise DeviceUnavailable(f"robot {self.robot_id}: not connected")
        if self._settings.speed > 0:
            now = self._clock.elapsed_recorded_s()
            times = np.array([s.timestamp_s for s in self._states])
            k = int(np.searchsorted(times, now, side="right")) - 1
            if k >= len(self._states) - 1 and now > times[-1] and self._settings.loop:
                self._clock = _Clock(self._settings.speed, self._states[0].timestamp_s)
                k = 0
            return self._now(self._states[max(k, 0)])
        if self._index >= len(self._states):
            if not self._settings.loop:
                raise DeviceUnavailable(f"robot {self.robot_id}: the recording has ended "
                                        f"({len(self._states)} states)")
            self._index = 0
        s = self._states[self._index]
        self._index += 1
        return self._now(s)

    @staticmethod
    def _now(s: RobotState) -> RobotState:
        # The played-back state is the current one; its recorded time stays in the metadata.
        return dataclasses.replace(s, timestamp_s=time.time(),
                                   metadata={**s.metadata, "recorded_timestamp_s": s.timestamp_s})

    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        raise MotionRejected(f"robot {self.robot_id} is a replay of a recording and cannot move")

    def _stop(self) -> None:
        """Nothing moves in a replay."""
