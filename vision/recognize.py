"""Recognition of several part types in one call: which part is where, and how sure.

Every model searches the image (down to a lower score, so that near-misses of the other models
are seen too); matches of different models at the same place compete, the best one wins, and
its margin is its score minus the best other model's score there (the runner-up). A margin near
zero means the parts are hard to tell apart at that place.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from vision.errors import SettingsError
from vision.types import MIN_SCORE_FLOOR, FindResult, SearchParams


class PartLike(Protocol):
    """What recognition needs of a part model: a name, its teach ROI, and a search."""

    @property
    def name(self) -> str: ...

    @property
    def roi(self) -> tuple[float, float, float, float]: ...

    def find(self, image: NDArray[Any], search: SearchParams | None = None) -> FindResult: ...

RUNNER_UP_FACTOR = 0.6
"""Other models are searched down to this fraction of ``min_score`` to measure the margin."""


@dataclass
class Recognition:
    part: str
    u_px: float
    v_px: float
    angle_deg: float
    score: float
    margin: float
    runner_up: str | None
    runner_up_score: float

    def as_dict(self) -> dict[str, object]:
        return {"part": self.part, "u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg,
                "score": self.score, "margin": self.margin, "runner_up": self.runner_up,
                "runner_up_score": self.runner_up_score}


@dataclass
class RecognitionResult:
    matches: list[Recognition]
    timed_out: bool
    elapsed_s: float


def _same_place_px(m: PartLike) -> float:
    u, v, w, h = m.roi
    return min(w, h) / 3.0


def recognize(models: Sequence[PartLike], image: NDArray[np.uint8],
              search: SearchParams | None = None) -> RecognitionResult:
    """Find all ``models`` in ``image``; one answer per place, best part first by score."""
    sp = search or SearchParams()
    if not models:
        raise SettingsError("recognition needs at least one part model")
    names = [m.name for m in models]
    if len(set(names)) != len(names):
        raise SettingsError(f"part model names must differ to tell the parts apart (got {names})")
    t0 = time.perf_counter()
    low = replace(sp, min_score=max(sp.min_score * RUNNER_UP_FACTOR, MIN_SCORE_FLOOR), max_count=None)
    allm: list[tuple[float, str, float, float, float, float]] = []  # score, name, u, v, angle, radius
    timed_out = False
    for m in models:
        left = None if sp.timeout_s is None else sp.timeout_s - (time.perf_counter() - t0)
        if left is not None and left <= 0:
            timed_out = True
            break
        res = m.find(image, replace(low, timeout_s=left))
        timed_out |= res.timed_out
        r = _same_place_px(m)
        allm += [(mt.score, m.name, mt.u_px, mt.v_px, mt.angle_deg, r) for mt in res.matches]
    allm.sort(key=lambda t: -t[0])
    groups: list[list[tuple[float, str, float, float, float, float]]] = []
    for t in allm:
        for g in groups:
            lead = g[0]
            if (t[2] - lead[2]) ** 2 + (t[3] - lead[3]) ** 2 < max(t[5], lead[5]) ** 2:
                g.append(t)
                break
        else:
            groups.append([t])
    out: list[Recognition] = []
    for g in groups:
        win = g[0]
        if win[0] < sp.min_score:
            continue
        others = [t for t in g if t[1] != win[1]]
        ru = others[0] if others else None
        ru_score = ru[0] if ru else 0.0
        out.append(Recognition(win[1], win[2], win[3], win[4], win[0], win[0] - ru_score,
                               ru[1] if ru else None, ru_score))
    if sp.max_count is not None:
        out = out[:sp.max_count]
    return RecognitionResult(out, timed_out, time.perf_counter() - t0)
