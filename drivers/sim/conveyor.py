"""The virtual conveyor: a belt that carries parts along the robot base's +x in real time, and its encoder.

The belt's travel ``position_m(t)`` (metres since the world started, ``t`` the monotonic clock) is the
integral of its speed: a set speed (0-300 mm/s, changed at once by ``set_speed``) times
``1 + speed_variation * sin(2 pi t / variation_period_s)`` (a slowly varying belt, off by default).
The encoder counts ``ticks_per_m`` ticks per metre of travel; a camera frame carries the count
latched at its exposure (``latched_ticks``), off by a Gaussian latch jitter of
``latch_jitter_ms`` (1-sigma, default 0.2 ms: a hardware-triggered latch; at 300 mm/s that is
0.06 mm of belt).

Faults (``simulate_*``, for tests and the bench): the encoder stops counting while the belt moves,
the count jumps by a number of ticks, the belt stops; a part slips on the belt
(``ProductionParts.slip``). Lengths in the spec are millimetres, base frame.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_SPEED_MM_S = 300.0


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class BeltParts(_Strict):
    """The parts the belt brings: ``count`` of the scene's part at seeded random spacing, some touching."""

    count: int = Field(40, ge=0, le=1000)
    seed: int = Field(0, ge=0)
    spacing_mm: tuple[float, float] = (150.0, 400.0)
    """Centre-to-centre distance along the belt between successive parts, drawn uniformly, mm."""
    touching: float = Field(0.15, ge=0, le=1)
    """Fraction of the parts pushed against the part ahead (they touch)."""
    lane_y_mm: tuple[float, float] = (-75.0, 75.0)
    """The band of the belt (base y, mm) the parts lie in (a target may ride beside it)."""
    first_x_mm: float = 40.0
    """Where the first part lies at the start (base x, mm): in the camera's view, so that at speed 0
    the first parts lie still there."""


class BeltSpec(_Strict):
    """The scene's ``conveyor:`` section: the belt (base frame, mm), its speed and encoder, its parts."""

    x_mm: tuple[float, float] = (-400.0, 850.0)
    """Where the belt starts (parts come onto it) and ends (a part carried past it falls off), base x."""
    y_mm: tuple[float, float] = (-75.0, 75.0)
    """The belt's width, base y."""
    speed_mm_s: float = Field(100.0, ge=0, le=MAX_SPEED_MM_S)
    speed_variation: float = Field(0.0, ge=0, le=0.5)
    variation_period_s: float = Field(20.0, gt=0, le=3600)
    ticks_per_m: float = Field(10000.0, gt=0, le=1e7)
    latch_jitter_ms: float = Field(0.2, ge=0, le=100)
    pick_window_mm: tuple[float, float] = (350.0, 740.0)
    """Base x the robot can reach on the belt (a recipe's window by default)."""
    parts: BeltParts = BeltParts()

    @model_validator(mode="after")
    def _ordered(self) -> BeltSpec:
        for name in ("x_mm", "y_mm", "pick_window_mm", ("parts", "spacing_mm"), ("parts", "lane_y_mm")):
            lo, hi = getattr(self.parts, name[1]) if isinstance(name, tuple) else getattr(self, name)
            if not lo < hi:
                raise ValueError(f"{name if isinstance(name, str) else '.'.join(name)} must be [low, high], low < high")
        return self


def _check_speed(speed_mm_s: float) -> None:
    if not 0.0 <= speed_mm_s <= MAX_SPEED_MM_S or not math.isfinite(speed_mm_s):
        raise ValueError(f"belt speed {speed_mm_s} mm/s is outside 0..{MAX_SPEED_MM_S:g} mm/s")


class SimBelt:
    """The belt's motion and encoder (thread-safe). ``t`` is ``time.monotonic()`` seconds."""

    def __init__(self, spec: BeltSpec, seed: int) -> None:
        self.spec = spec
        self._lock = threading.Lock()
        self._t_set = time.monotonic()
        self._s_set = 0.0
        self._v_m_s = spec.speed_mm_s * 1e-3
        self._variation = spec.speed_variation
        self._rng = np.random.default_rng([seed, 0xBE17])
        self._encoder_stopped_at: int | None = None
        self._jump_ticks = 0
        self._speed_changed = False
        """Whether the speed was set after the start (the history since the start is then fixed)."""
        self.direction_base = np.array([1.0, 0.0, 0.0])

    # -- motion -----------------------------------------------------------------------------------
    def position_m(self, t: float | None = None) -> float:
        """Belt travel since the start, metres."""
        t = time.monotonic() if t is None else t
        with self._lock:
            return self._position(t)

    def _position(self, t: float) -> float:
        dt = t - self._t_set
        if self._variation == 0.0 or self._v_m_s == 0.0:
            return self._s_set + self._v_m_s * dt
        w = 2 * math.pi / self.spec.variation_period_s
        return self._s_set + self._v_m_s * (dt + self._variation * (1.0 - math.cos(w * dt)) / w)

    def speed_mm_s(self, t: float | None = None) -> float:
        t = time.monotonic() if t is None else t
        with self._lock:
            w = 2 * math.pi / self.spec.variation_period_s
            return 1e3 * self._v_m_s * (1.0 + self._variation * math.sin(w * (t - self._t_set)))

    def configure(self, speed_mm_s: float, variation: float | None = None) -> None:
        """The speed (and variation) the belt ran at since its start: a conveyor device's settings when it
        opens. The world is made by whichever of the cell's devices opens first, so without this the belt
        ran at the scene's speed until the conveyor opened (a belt configured at 0 had moved its parts
        tens of mm: not where the cell's first picture shows them). Once the speed was changed after the
        start, this changes it now, like ``set_speed``."""
        with self._lock:
            if not self._speed_changed:
                _check_speed(speed_mm_s)
                self._v_m_s = speed_mm_s * 1e-3
                if variation is not None:
                    self._variation = float(variation)
                return
        self.set_speed(speed_mm_s, variation)

    def set_speed(self, speed_mm_s: float, variation: float | None = None) -> None:
        """Change the set speed (mm/s, 0-300) now; ``variation``: the slow variation's amplitude (fraction)."""
        _check_speed(speed_mm_s)
        now = time.monotonic()
        with self._lock:
            self._speed_changed = True
            self._s_set = self._position(now)
            self._t_set = now
            self._v_m_s = speed_mm_s * 1e-3
            if variation is not None:
                self._variation = float(variation)

    # -- encoder ----------------------------------------------------------------------------------
    def ticks(self, t: float | None = None) -> int:
        """The encoder's count now (or at ``t``)."""
        t = time.monotonic() if t is None else t
        with self._lock:
            if self._encoder_stopped_at is not None:
                return self._encoder_stopped_at
            return int(math.floor(self._position(t) * self.spec.ticks_per_m)) + self._jump_ticks

    def latched_ticks(self, t: float) -> int:
        """The count a camera latches at an exposure at ``t`` (with the latch jitter)."""
        with self._lock:
            jitter_s = float(self._rng.normal(0.0, self.spec.latch_jitter_ms * 1e-3))
        return self.ticks(t + jitter_s)

    def simulate_encoder_stop(self) -> None:
        """The encoder stops counting (a broken coupling); the belt goes on."""
        count = self.ticks()
        with self._lock:
            self._encoder_stopped_at = count

    def simulate_count_jump(self, ticks: int) -> None:
        """The count jumps by ``ticks`` (electrical noise on the pulse lines)."""
        with self._lock:
            self._jump_ticks += int(ticks)

    def clear_faults(self) -> None:
        with self._lock:
            self._encoder_stopped_at = None
            self._jump_ticks = 0

    def carried(self, T: np.ndarray, s_m: float | None = None) -> np.ndarray:
        """Where a target riding the belt (a loop twice the belt's length; ``T`` its pose at the start) is
        after the belt's travel ``s_m`` (default now); on the return side it is far below, out of view."""
        x0, x1 = (v * 1e-3 for v in self.spec.x_mm)
        loop = 2 * (x1 - x0)
        s = self.position_m() if s_m is None else s_m
        x = x0 + (float(T[0, 3]) - x0 + s) % loop
        out = np.array(T, dtype=np.float64, copy=True)
        out[0, 3] = x
        if x > x1:
            out[2, 3] -= 1.0
        return out

    # -- truth ------------------------------------------------------------------------------------
    def truth(self) -> dict[str, object]:
        now = time.monotonic()
        return {"ticks": self.ticks(now), "speed_mm_s": self.speed_mm_s(now),
                "window_mm": list(self.spec.pick_window_mm), "position_mm": self.position_m(now) * 1e3,
                "ticks_per_m": self.spec.ticks_per_m, "direction_base": self.direction_base.tolist(),
                "belt_x_mm": list(self.spec.x_mm), "belt_y_mm": list(self.spec.y_mm),
                "encoder_stopped": self._encoder_stopped_at is not None, "count_jump_ticks": self._jump_ticks}


class BeltTracker:
    """A robot controller tracking the belt, as the world sees it (``SimWorld.tracker``).

    While it tracks, every pose the controller is commanded is carried along ``direction_base`` by the
    travel the encoder counted since tracking started (``ticks_per_m``: the controller's belt
    calibration, which may be wrong), at most ``most_m`` (the controller's tracking limit: beyond it
    the tool stays). ``stop`` freezes the offset (the tool stays where it is, a move under way goes on
    in its frame); ``settle`` (no move under way) hands the offset to the world's poses.
    """

    def __init__(self, belt: SimBelt | None, lock: threading.RLock) -> None:
        self.belt = belt
        self._lock = lock
        self._track: tuple[np.ndarray, float, int, float] | None = None
        self._frozen = np.zeros(3)

    @property
    def tracking(self) -> bool:
        return self._track is not None

    def shift(self) -> np.ndarray:
        """The tool's offset along the belt now (m, base frame)."""
        with self._lock:
            track, belt = self._track, self.belt
            if track is None or belt is None:
                return self._frozen.copy()
            direction, ticks_per_m, start, most_m = track
            return self._frozen + direction * float(np.clip((belt.ticks() - start) / ticks_per_m, -most_m, most_m))

    def shifted(self, T: np.ndarray) -> np.ndarray:
        out = np.array(T, dtype=np.float64, copy=True)
        out[:3, 3] += self.shift()
        return out

    def start(self, direction_base: np.ndarray, ticks_per_m: float, most_m: float) -> int:
        """Track from now (after ``settle``); the count tracking starts at."""
        if self.belt is None:
            raise ValueError("this scene has no conveyor to track")
        d = np.asarray(direction_base, dtype=np.float64)
        if not (np.all(np.isfinite(d)) and np.linalg.norm(d) > 0 and math.isfinite(ticks_per_m) and ticks_per_m > 0):
            raise ValueError("tracking needs a direction and a positive ticks_per_m")
        with self._lock:
            count = self.belt.ticks()
            self._track = (d / np.linalg.norm(d), float(ticks_per_m), count, float(most_m))
            return count

    def stop(self) -> None:
        """Stop following: the offset stays what it is now."""
        with self._lock:
            self._frozen = self.shift()
            self._track = None

    def settle(self) -> np.ndarray:
        """Stop tracking and give the offset to the caller (who adds it to its poses); zero after."""
        with self._lock:
            self.stop()
            out, self._frozen = self._frozen, np.zeros(3)
            return out
