"""A bumped camera on request: a shift along and a turn about the base frame's axes, now or as a ramp.

``POST /sim/faults`` sets it (cellctl's drift checks are tested against it). The fault is applied to
the camera's true pose: ``T_base_cam = [R_fault R | t + d]`` (the camera turns about its own
centre, about axes parallel to the base frame's), so what the camera sees moves while every
calibration stays what it was. A ramp goes linearly from the fault in force when it is set to the
new one over ``ramp_s`` seconds (a bracket warming up); the camera's pose is read per frame.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g


@dataclass(frozen=True)
class Fault:
    shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rot_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def as_array(self) -> NDArray[np.float64]:
        return np.array([*self.shift_mm, *self.rot_deg], dtype=np.float64)


class CameraFault:
    """The fault in force (thread-safe); ``apply`` to the camera's nominal pose."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._from = np.zeros(6)
        self._to = np.zeros(6)
        self._t0 = 0.0
        self._ramp_s = 0.0

    def set(self, fault: Fault, ramp_s: float = 0.0, now_s: float | None = None) -> None:
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            self._from = self._at(now)
            self._to = fault.as_array()
            self._t0, self._ramp_s = now, max(0.0, float(ramp_s))

    def _at(self, now: float) -> NDArray[np.float64]:
        if self._ramp_s <= 0.0:
            return self._to.copy()
        f = min(1.0, max(0.0, (now - self._t0) / self._ramp_s))
        return self._from + f * (self._to - self._from)

    def now(self, now_s: float | None = None) -> Fault:
        """The fault in force at ``now_s`` (monotonic seconds; default now)."""
        with self._lock:
            v = self._at(time.monotonic() if now_s is None else now_s)
        return Fault((float(v[0]), float(v[1]), float(v[2])), (float(v[3]), float(v[4]), float(v[5])))

    def state(self) -> dict[str, object]:
        f = self.now()
        with self._lock:
            target, ramp_s = self._to.tolist(), self._ramp_s
        return {"camera_shift_mm": list(f.shift_mm), "camera_rot_deg": list(f.rot_deg),
                "target_shift_mm": target[:3], "target_rot_deg": target[3:], "ramp_s": ramp_s}

    def apply(self, T_base_cam: NDArray[np.float64], now_s: float | None = None) -> NDArray[np.float64]:
        """The camera's true pose under the fault in force."""
        v = self.now(now_s).as_array()
        if not np.any(v):
            return T_base_cam
        R = g.rotvec_to_matrix(np.radians(v[3:]))
        T = np.array(T_base_cam, dtype=np.float64, copy=True)
        T[:3, :3] = R @ T[:3, :3]
        T[:3, 3] = T[:3, 3] + v[:3] * 1e-3
        return T
