"""Which part a production cycle picks, and what a run remembers of the parts it could not pick.

A part is known again from picture to picture by its reference point (base frame, mm): a match
within ``SAME_PART_MM`` of a part tried before is that part. A part whose grip failed more than
the gripper's ``retries`` times is skipped; a part whose pick poses are refused (envelope, tool
cone, a neighbour too near) is counted ``unreachable`` once per run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cellctl.pick.candidate import PickCandidate
from cellctl.production.records import Counters
from cellctl.production.vision import Picture

SAME_PART_MM = 8.0
"""A match this close to a part tried before is that part (for retries and skips)."""


@dataclass
class Tried:
    """A part whose grip failed: where it lies (base frame, mm) and how often it failed."""

    xy_mm: np.ndarray
    failures: int = 0


@dataclass
class Choice:
    """The run's memory of failed and unreachable parts (one per run; its thread only)."""

    retries: int
    """Failed grips of one part tried again before it is skipped."""
    tried: list[Tried] = field(default_factory=list)
    unreachable: list[np.ndarray] = field(default_factory=list)

    def choose(self, picture: Picture, counters: Counters) -> PickCandidate | None:
        """The best-scoring pickable part; the unreachable ones are counted once each per run."""
        chosen = None
        for c in picture.candidates:
            if c.problem is not None:
                xy = c.T_base_part[:2, 3] * 1e3
                if not any(float(np.linalg.norm(xy - seen)) < SAME_PART_MM for seen in self.unreachable):
                    self.unreachable.append(xy)
                    counters.unreachable += 1
                continue
            tried = self.tried_at(c)
            if chosen is None and (tried is None or tried.failures <= self.retries):
                chosen = c
        return chosen

    def why_none(self, picture: Picture) -> str:
        """Why no part of ``picture`` is pickable (the cycle record's detail)."""
        problems = [c.problem for c in picture.candidates if c.problem]
        skipped = len(picture.candidates) - len(problems)
        parts = []
        if problems:
            parts.append(f"{len(problems)} not pickable ({problems[0]})")
        if skipped:
            parts.append(f"{skipped} skipped after failed grips")
        return f"{len(picture.candidates)} part(s) found, none pickable: " + "; ".join(parts)

    def tried_at(self, cand: PickCandidate) -> Tried | None:
        xy = cand.T_base_part[:2, 3] * 1e3
        return next((t for t in self.tried if float(np.linalg.norm(t.xy_mm - xy)) < SAME_PART_MM), None)

    def grip_failed(self, cand: PickCandidate) -> int:
        """Count a failed grip of the part ``cand``; its failures so far (skip it beyond ``retries``)."""
        tried = self.tried_at(cand)
        if tried is None:
            tried = Tried(cand.T_base_part[:2, 3] * 1e3)
            self.tried.append(tried)
        tried.failures += 1
        return tried.failures
