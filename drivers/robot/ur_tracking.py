"""Host-side conveyor tracking for a UR arm over RTDE (``URRTDERobot.start_tracking``; docs/conveyor.md).

``ur_rtde`` has no call for the controller's own tracking (``track_conveyor_linear``), so cellctl tracks the
belt from the host, as ``ur_rtde``'s servo examples stream poses. The stream runs in the adapter's control
worker (``ur_track_stream``: its own process, so no GIL in the service delays a step); this side feeds it
through shared memory: the belt's count as cellctl reads it (``count``, the conveyor) with its speed (the
count's slope over ``SPEED_WINDOW_S``), and the tool's moves in the belt's frame. Each streamed pose is the
belt-frame position carried along ``direction_base`` by the count extrapolated ``lead_s`` ahead, at most
``most_m``; the orientation is the one tracking started with (a move while tracking does not turn the tool).

Safety: a move while tracking is checked where it starts and ends, at the belt's travel 0 and ``most_m``
(the envelope is a box: every pose between them is inside), and the worker checks every streamed pose
against the box before it sends it (outside: the stream ends and the arm stops). ``end`` (a Stop, or the end
of tracking) clears the shared ``active`` flag the worker reads before every send.

The tracking error is measured, not assumed: while no move is under way (the tool holding over or on the
part, the gripper closing), the arm's reported pose is compared with where the belt carries the belt-frame
pose by the count at the report's instant (mm; ``report``). Its along-belt part feeds a small integral term
that takes out the stream's latency. Units: poses 4x4 in metres, times ``time.monotonic`` seconds.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from drivers.errors import MotionRejected
from drivers.limits import MotionLimits
from drivers.robot.ur_track_stream import BAD, FAILED, MAXGAP, SENT, TrackShared
from drivers.robot_base import turn_deg

log = logging.getLogger(__name__)

PERIOD_S = 0.008
"""How often the worker streams a servoL pose (125 Hz: a CB3's RTDE rate; an e-Series runs 500 Hz)."""
LEAD_S = 0.030
"""How far ahead each streamed pose is predicted (s), and the servo step's time: the arm keeps moving on
along the belt when a step comes late by up to this (a loaded host), instead of halting at the last one."""
FEED_S = 0.004
"""How often the count is handed to the worker (s); a late one is extrapolated at the belt's speed."""
SPEED_WINDOW_S = 0.2
"""The belt's speed is the count's slope over this window (s)."""
MIN_SPEED_WINDOW_S = 0.1
"""The count's own slope is used once its samples span this (s); before, the last tracking's speed."""
LAG_GAIN = 0.05
"""Each measurement moves the streamed pose along the belt by this fraction of the arm's along-belt error."""
LAG_MAX_M = 0.01
"""The integral term's bound (m): a larger error is not the stream's latency but a fault."""
TURN_MAX_DEG = 0.5
"""A move while tracking keeps the tool's orientation within this (the stream carries one orientation)."""


class HostTracking:
    """One tracking of the belt: the count fed to the worker's stream, the belt-frame moves, the measured error."""

    def __init__(self, robot_id: str, shared: TrackShared, *, count: Callable[[], int],
                 direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                 T_belt_start: NDArray[np.float64], rotvec: list[float], limits: MotionLimits,
                 actual: Callable[[], tuple[NDArray[np.float64], float] | None], lag_m: float = 0.0,
                 speed_ticks_s: float = 0.0) -> None:
        self.robot_id, self.shared, self._count, self._actual, self.limits = robot_id, shared, count, actual, limits
        d = np.asarray(direction_base, dtype=np.float64)
        if not (np.all(np.isfinite(d)) and np.linalg.norm(d) > 0 and math.isfinite(ticks_per_m) and ticks_per_m > 0
                and math.isfinite(most_m) and most_m >= 0):
            raise MotionRejected(f"robot {robot_id}: tracking needs a direction, a positive ticks_per_m and a "
                                 "limit >= 0")
        self.direction = d / np.linalg.norm(d)
        self.ticks_per_m, self.most_m = float(ticks_per_m), float(most_m)
        self._T_start = np.asarray(T_belt_start, dtype=np.float64).copy()
        self._seg = (self._T_start[:3, 3].copy(), self._T_start[:3, 3].copy(), 0.0, 0.0)  # p0, p1, t0, duration
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._samples: list[tuple[float, int]] = []
        self._errors_mm: list[float] = []
        self._along_mm: list[float] = []
        """The error's along-belt part (mm; + the arm ahead of the belt): a steady lag shows in its mean."""
        self._feed_gap_s = 0.0
        """The longest interval between two count feeds (s): this process's stalls (its GIL, its scheduling)."""
        self._sample_age_s = 0.0
        """The oldest state sample a measurement used (s): the state stream's stalls (emulator, receiver)."""
        self._speed_prior = float(speed_ticks_s)
        """The belt's speed until the count's own window is long enough (the last tracking's, ticks/s)."""
        self._lag_m = float(np.clip(lag_m, -LAG_MAX_M, LAG_MAX_M))
        """The integral term, starting where the last tracking's ended (the stream's latency, learnt)."""
        self.ticks0 = int(count())
        self._samples.append((time.monotonic(), self.ticks0))
        self._check_segment(self._T_start[:3, 3])
        lim = limits
        shared.write(active=0.0, failed=0.0, t_count=time.monotonic(), ticks=self.ticks0, speed=self._speed_prior,
                     lag=self._lag_m,
                     ticks0=self.ticks0, tpm=self.ticks_per_m, most=self.most_m, period=PERIOD_S, lead=LEAD_S,
                     seg_t0=0.0, seg_dur=0.0, sent=0.0, last=0.0, maxgap=0.0, dir=list(self.direction),
                     p0=list(self._seg[0]),
                     p1=list(self._seg[1]), rot=list(rotvec),
                     box=[v * 1e-3 for v in (*lim.x_mm, *lim.y_mm, *lim.z_mm)], bad=[0.0, 0.0, 0.0])
        self._thread = threading.Thread(target=self._feed, name=f"ur-{robot_id}-belt-count")

    def begin(self) -> None:
        """Let the worker stream (the caller then sends ``track_begin``) and start feeding it the count."""
        self.shared.write(active=1.0)
        self._thread.start()

    # -- the belt ----------------------------------------------------------------------------------
    def speed_ticks_s(self) -> float:
        with self._lock:
            (t0, c0), (t1, c1) = self._samples[0], self._samples[-1]
        if t1 - t0 < MIN_SPEED_WINDOW_S and self._speed_prior > 0:
            return self._speed_prior  # a few ms of whole ticks: too coarse (4 ticks +- 1 at 100 mm/s)
        return (c1 - c0) / (t1 - t0) if t1 - t0 > 1e-3 else 0.0

    def _offset(self, ticks: float) -> NDArray[np.float64]:
        travel = float(np.clip((ticks - self.ticks0) / self.ticks_per_m, 0.0, self.most_m))
        out: NDArray[np.float64] = self.direction * travel
        return out

    def belt_position(self, t: float) -> NDArray[np.float64]:
        """The tool's position in the belt's frame at ``t`` (m): the move under way, or the position held."""
        with self._lock:
            p0, p1, t0, dur = self._seg
        s = 1.0 if dur <= 0 else min(1.0, max(0.0, (t - t0) / dur))
        out: NDArray[np.float64] = p0 + s * (p1 - p0)
        return out

    def _feed(self) -> None:
        last = time.monotonic()
        while not self._halt.wait(FEED_S):
            now = time.monotonic()
            self._feed_gap_s, last = max(self._feed_gap_s, now - last), now
            try:
                ticks = int(self._count())
            except Exception as exc:  # noqa: BLE001 - the stream ends saying why; the caller stops the arm
                log.error("robot %s: the belt's count could not be read while tracking: %s", self.robot_id, exc)
                self.shared.write(active=0.0, failed=3.0)
                return
            with self._lock:
                self._samples.append((now, ticks))
                while len(self._samples) > 2 and now - self._samples[0][0] > SPEED_WINDOW_S:
                    self._samples.pop(0)
            self._measure(now, ticks)
            self.shared.write(t_count=now, ticks=ticks, speed=self.speed_ticks_s(), lag=self._lag_m)

    def _measure(self, now: float, ticks: int) -> None:
        got = self._actual()
        if got is None:
            return
        T_actual, t_sample = got
        with self._lock:
            _p0, _p1, t0, dur = self._seg
        if t_sample < t0 + dur + 2 * LEAD_S:
            return  # a move under way: the error that counts is the one while the tool holds on the part
        ticks_then = ticks - self.speed_ticks_s() * max(0.0, now - t_sample)
        error = T_actual[:3, 3] - (self.belt_position(t_sample) + self._offset(ticks_then))
        along = float(error @ self.direction)
        self._lag_m = float(np.clip(self._lag_m - LAG_GAIN * along, -LAG_MAX_M, LAG_MAX_M))
        with self._lock:
            self._errors_mm.append(1e3 * float(np.linalg.norm(error)))
            self._along_mm.append(1e3 * along)
            self._sample_age_s = max(self._sample_age_s, now - t_sample)

    # -- the caller's side ---------------------------------------------------------------------------
    def _check_segment(self, p: NDArray[np.float64]) -> None:
        for travel in (0.0, self.most_m):  # the box is convex: the poses between these are inside too
            T = self._T_start.copy()
            T[:3, 3] = p + self.direction * travel
            self.limits.check_pose(T)

    def move(self, T_belt: NDArray[np.float64], speed_m_s: float) -> float:
        """Start a straight move to ``T_belt`` (belt frame) at ``speed_m_s``; its duration (s)."""
        turn = turn_deg(self._T_start, T_belt)
        if turn > TURN_MAX_DEG:
            raise MotionRejected(f"robot {self.robot_id}: a move while tracking the belt turns the tool {turn:.1f} "
                                 f"deg; turn it before tracking starts")
        now = time.monotonic()
        start, end = self.belt_position(now), np.asarray(T_belt[:3, 3], dtype=np.float64).copy()
        self._check_segment(end)
        duration = float(np.linalg.norm(end - start)) / speed_m_s
        with self._lock:
            self._seg = (start, end, now, duration)
        self.shared.write(p0=list(start), p1=list(end), seg_t0=now, seg_dur=duration)
        return duration

    def arrived_within_mm(self, T_actual: NDArray[np.float64], t_sample: float) -> float:
        """How far (mm) the reported pose is from the move's end, carried by the belt to ``t_sample``."""
        ticks = self._count() - self.speed_ticks_s() * max(0.0, time.monotonic() - t_sample)
        with self._lock:
            end = self._seg[1]
        return 1e3 * float(np.linalg.norm(T_actual[:3, 3] - (end + self._offset(ticks))))

    @property
    def error(self) -> str | None:
        """Why the stream ended by itself, or None."""
        v = self.shared.read()
        if not v[FAILED]:
            return None
        if v[FAILED] == 1.0:
            x, y, z = (1e3 * c for c in v[BAD:BAD + 3])
            return (f"the tracked pose ({x:.1f}, {y:.1f}, {z:.1f}) mm left the envelope; the stream ended and the "
                    "arm was stopped")
        if v[FAILED] == 3.0:
            return "the belt's count could not be read while tracking; the stream ended"
        return "streaming to the controller failed; the stream ended"

    def end(self) -> None:
        """No pose is streamed after this; the count feeder is joined (from any thread but its own)."""
        self.shared.end()
        self._halt.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(1.0)

    @property
    def lag_m(self) -> float:
        return self._lag_m

    def report(self) -> dict[str, float | int]:
        """The measured tracking error: samples, RMS and max (mm), the along-belt part's mean (mm; + the arm
        ahead: a steady lag or lead), and the servo steps streamed; where a stall would show: the worker's longest
        interval between two steps, this process's between two count feeds, the oldest state sample used (ms)."""
        with self._lock:
            e, along = list(self._errors_mm), list(self._along_mm)
        v = self.shared.read()
        stalls = {"stream_gap_ms": round(1e3 * v[MAXGAP], 1), "feed_gap_ms": round(1e3 * self._feed_gap_s, 1),
                  "sample_age_ms": round(1e3 * self._sample_age_s, 1)}
        if not e:
            return {"samples": 0, "rms_mm": math.nan, "max_mm": math.nan, "mean_along_mm": math.nan,
                    "servo_steps": int(v[SENT]), **stalls}
        return {"samples": len(e), "rms_mm": round(float(np.sqrt(np.mean(np.square(e)))), 3),
                "max_mm": round(float(np.max(e)), 3), "mean_along_mm": round(float(np.mean(along)), 3),
                "servo_steps": int(v[SENT]), **stalls}
