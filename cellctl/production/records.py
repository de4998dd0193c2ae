"""A run's counters, cycle times and cycle records (with their CSV form).

Cycle times are over the run's *placed* cycles: ``median`` and ``p95`` of the whole cycle, and the
medians of the time it waited for vision (capture + search), the time the robot moved and the
time the gripper acted or settled (milliseconds).
"""

from __future__ import annotations

import csv
import io
import math
import threading
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

RESULTS = ("placed", "grip_failed", "skipped", "empty", "none_pickable", "stopped", "vision_failed", "interrupted",
           "not_recognized", "missed_window")
POSE_KEYS = ("x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")
"""A pose's CSV columns: the tool's position (mm, base frame) and its orientation as UR's rotation vector
(axis times angle, radians): ``rz_rad`` is that vector's z component, not a yaw angle."""
CSV_COLUMNS = ("n", "t", "result", "slot", "score", *(f"pick_{k}" for k in POSE_KEYS),
               *(f"place_{k}" for k in POSE_KEYS), "sigma_mm", "sigma_yaw_deg",
               "cycle_ms", "vision_ms", "motion_ms", "gripper_ms", "frame_id", "detail")


@dataclass
class Counters:
    picked: int = 0
    placed: int = 0
    grip_failures: int = 0
    retries: int = 0
    skipped: int = 0
    empty_area: int = 0
    unreachable: int = 0
    missed_window: int = 0
    """Parts on a belt that left the pick window unpicked (docs/conveyor.md)."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class CycleTimes:
    """Durations (ms) of the placed cycles."""

    total: list[float] = field(default_factory=list)
    vision: list[float] = field(default_factory=list)
    motion: list[float] = field(default_factory=list)
    gripper: list[float] = field(default_factory=list)

    def add(self, durations_ms: dict[str, float]) -> None:
        self.total.append(durations_ms["cycle"])
        self.vision.append(durations_ms["vision"])
        self.motion.append(durations_ms["motion"])
        self.gripper.append(durations_ms["gripper"])

    def summary(self) -> dict[str, float | None]:
        def med(v: list[float]) -> float | None:
            return float(np.median(v)) if v else None

        return {"median": med(self.total),
                "p95": float(np.percentile(self.total, 95)) if self.total else None,
                "vision_median": med(self.vision), "motion_median": med(self.motion),
                "gripper_median": med(self.gripper)}


class Durations:
    """The time one cycle spent waiting for vision, moving, and gripping (seconds, summed)."""

    def __init__(self) -> None:
        self.vision_s = 0.0
        self.motion_s = 0.0
        self.gripper_s = 0.0
        self._lock = threading.Lock()

    def add(self, what: str, seconds: float) -> None:
        with self._lock:
            setattr(self, f"{what}_s", getattr(self, f"{what}_s") + seconds)

    def as_ms(self, cycle_s: float) -> dict[str, float]:
        return {"cycle": cycle_s * 1e3, "vision": self.vision_s * 1e3, "motion": self.motion_s * 1e3,
                "gripper": self.gripper_s * 1e3}


def seen_fields(cand: Any, picture: Any, T_place: Any) -> dict[str, Any]:
    """A cycle record's fields from what it saw and did: the chosen part (``PickCandidate``), the
    picture (``vision.Picture``) and the place pose (4x4, metres); None where there is none."""
    from cellctl.motion import pose_json

    return {
        "score": None if cand is None else float(cand.match.score),
        "pick_pose": None if cand is None else pose_json(cand.T_pick),
        "place_pose": None if T_place is None else pose_json(T_place),
        "uncertainty": None if cand is None else {"sigma_mm": cand.sigma_mm,
                                                  "sigma_yaw_deg": cand.sigma_yaw_deg},
        "frame_id": None if picture is None else picture.frame_id,
        "calibration": None if picture is None else picture.calibration,
        "found": None if picture is None else picture.found,
        "fixture": None if picture is None else picture.fixture,
    }


def clean(value: Any) -> Any:
    """JSON-safe: NaN and infinities become None (a record is stored and served as strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [clean(v) for v in value]
    return value


def to_csv(records: list[dict[str, Any]]) -> str:
    """The cycle records as CSV (one row per cycle; the pick and place poses whole: ``POSE_KEYS``)."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in records:
        pick, place = r.get("pick_pose") or {}, r.get("place_pose") or {}
        unc = r.get("uncertainty") or {}
        d = r.get("durations_ms") or {}
        sigma = unc.get("sigma_mm")
        w.writerow([r["n"], f"{r['t']:.3f}", r["result"], _v(r.get("slot")), _v(r.get("score")),
                    *(_v(pick.get(k)) for k in POSE_KEYS), *(_v(place.get(k)) for k in POSE_KEYS),
                    "" if not sigma else " ".join(f"{s:.4f}" for s in sigma if s is not None),
                    _v(unc.get("sigma_yaw_deg")), _v(d.get("cycle")), _v(d.get("vision")), _v(d.get("motion")),
                    _v(d.get("gripper")), _v(r.get("frame_id")), r.get("detail") or ""])
    return out.getvalue()


def _v(x: Any) -> str:
    if x is None:
        return ""
    if isinstance(x, float):
        return f"{x + 0.0:.4f}".replace("-0.0000", "0.0000")  # no "-0.0000" for a component that is 0
    return str(x)
