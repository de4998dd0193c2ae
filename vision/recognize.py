"""Recognition of several part types in one call: which part is where, and how sure.

Every model searches the image (down to a lower score, so that near-misses of the other models
are seen too); matches of different models at the same place compete, the best one wins, and
its margin is its score minus the best other model's score there (the runner-up). A margin near
zero means the parts are hard to tell apart at that place.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from vision.errors import SettingsError
from vision.types import (
    MIN_SCORE_FLOOR,
    Candidate,
    FindResult,
    Match,
    Rejected,
    SearchParams,
    finite_or_none,
    no_match_reason,
)


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
    scale: float = 1.0
    mirrored: bool = False
    n_points: int = 0
    """Model points that agreed with an image edge (0 for a blob model)."""
    sigma_angle_deg: float = float("nan")
    """1-sigma of ``angle_deg`` (``Match.sigma_angle_deg``; NaN for a blob model)."""
    scores: dict[str, float] = field(default_factory=dict)
    """The verification's scores (``Match.scores``)."""
    sigma_px: float = float("nan")
    """1-sigma of the point (``Match.sigma_px``, px; NaN when unknown)."""
    refine: str | None = None
    """``Match.refine``: ``"rim"`` when the point is the round part's rim centre (then ``sigma_px`` is its)."""

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = {
            "part": self.part, "u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg,
            "score": self.score, "margin": self.margin, "runner_up": self.runner_up,
            "runner_up_score": self.runner_up_score, "scale": self.scale, "mirrored": self.mirrored,
            "n_points": self.n_points, "sigma_angle_deg": finite_or_none(self.sigma_angle_deg),
            "sigma_px": finite_or_none(self.sigma_px), "scores": dict(self.scores)}
        if self.refine is not None:
            out["refine"] = self.refine
        return out


@dataclass
class RecognitionResult:
    matches: list[Recognition]
    timed_out: bool
    elapsed_s: float
    best_rejected: Candidate | None = None
    """The best candidate of any model that stayed below ``min_score``."""
    min_score: float = 0.5
    rejected: list[Rejected] = field(default_factory=list)
    """Candidates that reached ``min_score`` and failed the verification (each part's, best first)."""

    def reason(self) -> str | None:
        """Why nothing was found, in one line (``None`` when something was)."""
        return no_match_reason(self.timed_out, self.best_rejected, self.min_score, self.rejected) \
            if not self.matches else None


def _same_place_px(m: PartLike) -> float:
    u, v, w, h = m.roi
    return min(w, h) / 3.0


_Hit = tuple[float, str, Match, float]  # score, part name, match, same-place radius


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
    allm: list[_Hit] = []
    rejected: list[Rejected] = []
    timed_out = False
    best: Candidate | None = None
    searched_s = 0.0  # the models' own search time: a first search's one-off loading is not in it
    for m in models:
        left = None if sp.timeout_s is None else max(sp.timeout_s - searched_s, 0.0)
        if left is not None and left <= 0:
            timed_out = True
            break
        res = m.find(image, replace(low, timeout_s=left))
        searched_s += res.elapsed_s
        timed_out |= res.timed_out
        r = _same_place_px(m)
        allm += [(mt.score, m.name, mt, r) for mt in res.matches]
        below = [Candidate(mt.u_px, mt.v_px, mt.angle_deg, mt.score) for mt in res.matches
                 if mt.score < sp.min_score]
        if res.best_rejected is not None:
            below.append(res.best_rejected)
        for c in below:
            if best is None or c.score > best.score:
                best = c
    allm.sort(key=lambda t: -t[0])
    groups: list[list[_Hit]] = []
    for t in allm:
        for g in groups:
            lead = g[0]
            if (t[2].u_px - lead[2].u_px) ** 2 + (t[2].v_px - lead[2].v_px) ** 2 < max(t[3], lead[3]) ** 2:
                g.append(t)
                break
        else:
            groups.append([t])
    out: list[Recognition] = []
    for g in groups:
        score, name, mt, _ = g[0]
        if score < sp.min_score:
            continue
        short = [k for k in ("coverage", "unclaimed") if mt.scores.get(k, 1.0) < sp.min_score]
        if short:  # the verification ran at the lowered score: its fractions answer to the one asked
            rejected.append(Rejected(mt.u_px, mt.v_px, mt.angle_deg, score, mt.mirrored, dict(mt.scores),
                                     f"{short[0]} {mt.scores[short[0]]:.2f} < min_score {sp.min_score:g}"))
            continue
        others = [t for t in g if t[1] != name]
        ru = others[0] if others else None
        ru_score = ru[0] if ru else 0.0
        out.append(Recognition(name, mt.u_px, mt.v_px, mt.angle_deg, score, score - ru_score,
                               ru[1] if ru else None, ru_score, mt.scale, mt.mirrored, mt.n_points,
                               mt.sigma_angle_deg, dict(mt.scores), mt.sigma_px, mt.refine))
    if sp.max_count is not None:
        out = out[:sp.max_count]
    rejected.sort(key=lambda x: -x.score)
    return RecognitionResult(out, timed_out, time.perf_counter() - t0, best, sp.min_score, rejected)
