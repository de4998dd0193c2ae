"""A belt's parts as cellctl tracks them: the queue in the belt's frame, the meeting plan, the encoder's health.

Belt coordinates: a part seen in a frame latched at count ``c`` at ``T_base_part`` (4x4, metres) is at
``T_base_part`` moved along ``direction_base`` by ``(c_now - c) / ticks_per_m`` metres at count
``c_now`` (the belt's calibration, ``conveyor-calibrate``). The queue keeps one entry per part: a part
seen again (its predicted position within ``MERGE_SIGMAS`` of its uncertainty, at least
``MERGE_MIN_MM`` and at most ``MERGE_MAX_MM``, and its yaw within ``MERGE_DEG``) updates its entry
with the freshest sighting;
``Sighting.offsets_mm`` says how far from where the count put it each was seen again.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellctl.pick.candidate import PickCandidate
from cellctl.pick.pose import PartPose, grasp
from cellctl.pick.recipe import Recipe
from drivers.base import MotionLimits, MotionRejected

MERGE_SIGMAS = 4.0
MERGE_MIN_MM = 6.0
MERGE_MAX_MM = 15.0
MERGE_DEG = 12.0


@dataclass(frozen=True)
class BeltCalibration:
    """The belt in the base frame: its direction (unit vector) and its encoder's ticks per metre."""

    direction_base: NDArray[np.float64]
    ticks_per_m: float
    calibration_id: int | None = None
    sigma_ticks_per_m: float = 0.0
    sigma_direction_deg: float = 0.0

    def shift(self, ticks: float) -> NDArray[np.float64]:
        """The belt's travel over ``ticks`` counts, base frame, metres."""
        return self.direction_base * (ticks / self.ticks_per_m)

    def moved(self, T: NDArray[np.float64], ticks: float) -> NDArray[np.float64]:
        out = np.array(T, dtype=np.float64, copy=True)
        out[:3, 3] += self.shift(ticks)
        return out

    @classmethod
    def from_result(cls, result: dict[str, Any], calibration_id: int | None = None) -> BeltCalibration:
        d = np.asarray(result["direction_base"], dtype=np.float64)
        return cls(d / np.linalg.norm(d), float(result["ticks_per_m"]), calibration_id,
                   float(result.get("sigma_ticks_per_m") or 0.0), float(result.get("sigma_direction_deg") or 0.0))


@dataclass
class BeltPart:
    """One queued part: its candidate (poses at the count ``ticks``) and what was seen of it."""

    key: int
    cand: PickCandidate
    ticks: int
    frame_id: int | None
    sightings: int = 1
    first_ticks: int = 0
    picture: Any = None

    def T_at(self, belt: BeltCalibration, ticks: int, T: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """A pose of this part (default its reference point) carried to count ``ticks``."""
        return belt.moved(self.cand.T_base_part if T is None else T, ticks - self.ticks)

    def x_at(self, belt: BeltCalibration, ticks: int) -> float:
        """The part's reference point along base x at count ``ticks``, mm."""
        return float(self.T_at(belt, ticks)[0, 3]) * 1e3


@dataclass
class Sighting:
    """What adding one picture's parts did: new parts, parts seen again, and how far off the count put them."""

    added: int = 0
    merged: int = 0
    done: int = 0
    """Parts seen that were picked or given up already (a picture taken before)."""
    offsets_mm: list[float] = field(default_factory=list)
    """For each part seen again: where it was seen minus where the count said, along the belt, mm."""


class BeltQueue:
    """The parts seen on the belt and not yet picked or given up (thread-safe)."""

    def __init__(self, belt: BeltCalibration) -> None:
        self.belt = belt
        self._parts: list[BeltPart] = []
        self._done: deque[BeltPart] = deque(maxlen=64)
        """Parts picked or given up: a late picture of one adds nothing."""
        self._lock = threading.Lock()
        self._next_key = 1

    def __len__(self) -> int:
        with self._lock:
            return len(self._parts)

    def add(self, cands: list[PickCandidate], ticks: int, frame_id: int | None, picture: Any = None) -> Sighting:
        """One picture's parts, latched at ``ticks``: each merged with its queued entry or added."""
        out = Sighting()
        with self._lock:
            for c in cands:
                if self._match(c, ticks, list(self._done))[0] is not None:
                    out.done += 1
                    continue
                hit, off = self._match(c, ticks, self._parts)
                if hit is None:
                    self._parts.append(BeltPart(self._next_key, c, ticks, frame_id, 1, ticks, picture))
                    self._next_key += 1
                    out.added += 1
                    continue
                out.merged += 1
                out.offsets_mm.append(off)
                hit.cand, hit.ticks, hit.frame_id, hit.picture = c, ticks, frame_id, picture  # the freshest sighting
                hit.sightings += 1
        return out

    def _match(self, c: PickCandidate, ticks: int, parts: list[BeltPart]) -> tuple[BeltPart | None, float]:
        """The queued part this candidate is (its predicted position and yaw agree), and the offset along."""
        best, best_d, best_off = None, math.inf, 0.0
        sigma = float(np.hypot(c.sigma_mm[0], c.sigma_mm[1])) if len(c.sigma_mm) >= 2 else 0.0
        radius = min(MERGE_MAX_MM, max(MERGE_MIN_MM, MERGE_SIGMAS * sigma))
        for p in parts:
            diff = (c.T_base_part[:3, 3] - p.T_at(self.belt, ticks)[:3, 3]) * 1e3
            along = float(diff @ self.belt.direction_base)
            across = float(np.linalg.norm(diff - along * self.belt.direction_base))
            dyaw = abs((c.base_yaw_deg - p.cand.base_yaw_deg + 180.0) % 360.0 - 180.0)
            if max(abs(along), across) <= radius and dyaw <= MERGE_DEG and abs(along) + across < best_d:
                best, best_d, best_off = p, abs(along) + across, along
        return best, best_off

    def parts(self) -> list[BeltPart]:
        with self._lock:
            return list(self._parts)

    def remove(self, part: BeltPart) -> None:
        """The part is picked or given up: out of the queue, and not added again."""
        with self._lock:
            self._parts = [p for p in self._parts if p.key != part.key]
            self._done.append(part)

    def downstream_first(self, ticks: int) -> list[BeltPart]:
        """The queued parts (copies: a later sighting does not change them under the caller), the one furthest
        along the belt at ``ticks`` first."""
        with self._lock:
            return sorted((replace(p) for p in self._parts), key=lambda p: -p.x_at(self.belt, ticks))


@dataclass(frozen=True)
class Meeting:
    """Where and when the robot meets a part: the count at which the part is under the approach pose."""

    ticks: int
    x_mm: float
    wait_s: float


def plan_meeting(part: BeltPart, belt: BeltCalibration, ticks_now: int, speed_mm_s: float,
                 tool_xyz_m: NDArray[np.float64], approach_z_m: float, window_mm: tuple[float, float],
                 move_speed_m_s: float, accel_m_s2: float, follow_s: float,
                 travel: Callable[[NDArray[np.float64]], float] | None = None, lead_s: float = 0.0) -> Meeting | str:
    """The earliest meeting inside the window, or why there is none now: ``Missed`` when the part will leave
    the window before the robot can meet it, a plain ``str`` when it may still come (the belt stopped).

    The part moves at ``speed_mm_s`` (the belt's measured speed); the robot needs the straight move from
    ``tool_xyz_m`` to above the meeting point, then ``follow_s`` following the part (down, the gripper's
    close, up): the part must still be inside the window (``window_mm``, base x) at the end of it.
    The move's time: ``travel`` (the robot's own timing of a move to the approach pose ``T`` above the
    meeting point, 4x4: ``RobotBase.linear_move_s``) when given, else the distance at ``move_speed_m_s``
    with ``accel_m_s2`` ramps; ``lead_s`` is added either way (what passes between this plan and the move's
    start, and the host's delays of a move).
    """
    x_now = part.x_at(belt, ticks_now)
    x0, x1 = window_mm
    v = max(0.0, speed_mm_s)
    follow_mm = v * follow_s
    if x_now + follow_mm > x1:
        return Missed(f"it is at x = {x_now:.0f} mm: past the window's end ({x1:.0f} mm) before a grip could finish")
    T = part.T_at(belt, ticks_now, part.cand.T_approach)
    start = np.asarray(tool_xyz_m, dtype=np.float64)

    def travel_s(x_mm: float) -> float:
        target = T.copy()
        target[0, 3] += (x_mm - x_now) * 1e-3
        target[2, 3] = approach_z_m
        if travel is not None:
            return lead_s + travel(target)
        d = float(np.linalg.norm(target[:3, 3] - start))
        return lead_s + d / move_speed_m_s + move_speed_m_s / accel_m_s2

    if v < 1.0:  # the belt stands (or creeps): meet the part where it lies, if it lies in the window
        if x0 <= x_now <= x1 - follow_mm:
            return Meeting(ticks_now, x_now, 0.0)
        return (f"it lies still at x = {x_now:.0f} mm, upstream of the window ({x0:.0f} mm): the belt stopped"
                if x_now < x0 else Missed(f"it lies still at x = {x_now:.0f} mm, past the window"))
    x = max(x0, x_now)
    while x + follow_mm <= x1:
        t = (x - x_now) / v
        need = travel_s(x)
        if need <= t:
            return Meeting(ticks_now + int(round((x - x_now) * 1e-3 * belt.ticks_per_m)), x, t - need)
        x += max(1.0, v * (need - t))  # where the part will be when the robot could be there
    return Missed(f"the robot cannot reach it inside the window (x = {x_now:.0f} mm now, window "
                  f"{x0:.0f}..{x1:.0f} mm, belt {v:.0f} mm/s)")


def grasp_near(recipe: Recipe, cand: PickCandidate, T_tool: NDArray[np.float64], limits: MotionLimits) -> PickCandidate:
    """``cand`` with the gripper's symmetric grasp nearest the yaw of the tool at ``T_tool`` (a parallel gripper
    then turns at most 90 deg on its way to the part: the turn overlaps less of the approach); ``cand`` itself
    when it has that grasp already or a pose of the other is refused by the envelope (``limits``)."""
    T = np.asarray(T_tool)
    g = grasp(recipe, PartPose(cand.T_base_part, math.radians(cand.base_yaw_deg), cand.sigma_mm),
              math.atan2(float(T[1, 0]), float(T[0, 0])))
    if abs((math.degrees(g.gripper_yaw_rad) - cand.gripper_yaw_deg + 180.0) % 360.0 - 180.0) < 1e-6:
        return cand
    try:
        for pose in (g.T_pick, g.T_approach):
            limits.check_pose(pose)
    except MotionRejected:
        return cand
    return replace(cand, T_part_grip=g.T_part_grip, T_pick=g.T_pick, T_approach=g.T_approach,
                   gripper_yaw_deg=math.degrees(g.gripper_yaw_rad))


class Missed(str):
    """Why a part cannot be met: it will leave the window first (``missed_window``)."""


class BeltWatch:
    """The encoder's count against the clock: the belt's speed, and a count that jumps.

    Thread-safe: the run's thread and its count watcher read and sample the count (``read``, one read at a
    time) while others (REST's ``GET /production``, a PLC) read the speed; the samples are read and written
    under one lock (a reader copies them, then computes)."""

    def __init__(self, ticks_per_m: float, max_speed_mm_s: float = 300.0) -> None:
        self.ticks_per_m = ticks_per_m
        self.max_speed_mm_s = max_speed_mm_s
        self._read_lock = threading.Lock()
        """Held from the start of a count's read to its sample (``read``): one read at a time."""
        self._lock = threading.Lock()
        self._samples: deque[tuple[float, int]] = deque(maxlen=400)
        """(monotonic s, count) of the last reads, oldest first (under ``_lock``)."""
        self._read_from_s: float | None = None
        """When the last count's read began (monotonic s): the count was taken between then and its sample's time."""

    def read(self, count: Callable[[], int]) -> tuple[int, str | None]:
        """Read the count now (``count``: the conveyor's ``ticks``) and sample it: (the count, why it is wrong or
        None). Reads are one at a time, from the read's start to its sample: the samples stay in the order of
        their reads (two reads interleaved could sample an older count just after a newer one: at speed, tens of
        ticks in a few ms, a false jump), and the conveyor's driver is read by one of the run's threads at once."""
        with self._read_lock:
            read_from_s = time.monotonic()
            ticks = count()
            return ticks, self.sample(ticks, read_from_s=read_from_s)

    def sample(self, ticks: int, t: float | None = None, read_from_s: float | None = None) -> str | None:
        """Record the count read between ``read_from_s`` and ``t`` (default: now); why it is wrong (a jump:
        faster than any belt here), or None. The interval between two counts is taken at its longest, from
        the start of the last read to the end of this one: a thread the machine holds between reading the
        count and reading the clock must not make an ordinary count look like a jump."""
        t = time.monotonic() if t is None else t
        with self._lock:
            last = self._samples[-1] if self._samples else None
            last_read_from_s = self._read_from_s
            self._samples.append((t, ticks))
            self._read_from_s = read_from_s
        if last is None:
            return None
        t0, c0 = last
        dt = max(t - (t0 if last_read_from_s is None else last_read_from_s), 1e-3)
        speed = abs(ticks - c0) / self.ticks_per_m * 1e3 / dt
        if abs(ticks - c0) > 20 and speed > 2.0 * self.max_speed_mm_s:
            return (f"the encoder count jumped by {ticks - c0} ticks in {dt * 1e3:.0f} ms "
                    f"({speed:.0f} mm/s, more than twice the belt's {self.max_speed_mm_s:.0f} mm/s): "
                    "check the encoder's wiring and shield, then calibrate the belt again")
        return None

    def speed_mm_s(self, over_s: float = 0.5) -> float:
        """The belt's speed from the counts of the last ``over_s`` seconds, mm/s (0 with too few)."""
        with self._lock:
            samples = tuple(self._samples)
        if len(samples) < 2:
            return 0.0
        t1, c1 = samples[-1]
        t0, c0 = samples[0]
        for t, c in reversed(samples):
            t0, c0 = t, c
            if t1 - t >= over_s:
                break
        if t1 - t0 <= 0:
            return 0.0
        return (c1 - c0) / self.ticks_per_m * 1e3 / (t1 - t0)
