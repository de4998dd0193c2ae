"""Where a production scene's parts lie at the start: seeded, deterministic scatters in the pick area and
along a conveyor's belt (``drivers.sim.production.ProductionParts`` makes its parts of them).

A pose here is ``(x_mm, y_mm, yaw_deg)`` of a part lying flat (base frame, mm and degrees; the part's
reference point, x along its outline's x). Two parts overlap when points sampled along their outlines every
``SAMPLE_MM`` come nearer than a margin: none is placed overlapping another, and some are slid or pushed until
they touch a neighbour or the area's edge.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from drivers.sim.conveyor import BeltParts
from drivers.sim.production_spec import AreaSpec, ProductionSpec

SAMPLE_MM = 1.0
"""Spacing of the points that test two parts for overlap, mm."""
Pose2 = tuple[float, float, float]
"""A part lying flat: (x_mm, y_mm, yaw_deg), base frame."""


class PartScatter:
    """The seeded scatters of one production scene's part (``spec.part``'s outline, ``spec.scatter``'s seed)."""

    def __init__(self, spec: ProductionSpec) -> None:
        self.spec = spec
        self._samples = _sample_points(spec.part.outline_mm, spec.part.holes_mm)

    def in_area(self) -> list[Pose2]:
        """Seeded poses in the pick area: no overlap, some touching a neighbour or the area's edge."""
        sc = self.spec.scatter
        rng = np.random.default_rng([sc.seed, 0x5CA7])
        area = self.spec.pick_area
        placed: list[Pose2] = []
        clear = sc.clear_part
        if clear is not None and sc.count > 0:
            placed.append((clear.x_mm, clear.y_mm, clear.angle_deg))
        tries = 0
        while len(placed) < sc.count:
            tries += 1
            if tries > 20000:
                raise ValueError(f"production scene: {sc.count} parts do not fit in the pick area "
                                 f"({len(placed)} placed); enlarge pick_area or lower scatter.count")
            cand = (float(rng.uniform(*area.x_mm)), float(rng.uniform(*area.y_mm)), float(rng.uniform(-180, 180)))
            if not self._fits(cand, placed, area):
                continue
            if rng.uniform() < sc.touching:
                cand = self._slide(cand, placed, area, rng)
            placed.append(cand)
        return placed

    def on_belt(self, bp: BeltParts) -> list[Pose2]:
        """Seeded poses along the belt from its ``first_x_mm`` upstream (-x): random spacing, some parts
        pushed against the one ahead (touching), none overlapping; all inside the parts' lane. The first part
        lies upright (its outline's x along base x): the one a user teaches with the belt still."""
        rng = np.random.default_rng([bp.seed, 0xC0])
        r = self.spec.part_radius_mm()
        y_lo, y_hi = bp.lane_y_mm[0] + r, bp.lane_y_mm[1] - r
        placed: list[Pose2] = []
        x = bp.first_x_mm
        for k in range(bp.count):
            y = float(rng.uniform(y_lo, y_hi)) if y_hi > y_lo else 0.5 * sum(bp.lane_y_mm)
            a = float(rng.uniform(-180, 180)) if k > 0 else 0.0  # the first one upright: to be taught
            if k > 0:
                x = placed[-1][0] - float(rng.uniform(*bp.spacing_mm))
                if rng.uniform() < bp.touching:
                    while x + SAMPLE_MM < placed[-1][0] and self._clear((x + SAMPLE_MM, y, a), placed[-2:]):
                        x += SAMPLE_MM  # pushed up to the part ahead
            while not self._clear((x, y, a), placed[-2:]):
                x -= SAMPLE_MM
            placed.append((x, y, a))
        return placed

    def _clear(self, cand: Pose2, others: list[Pose2]) -> bool:
        pts = self._world_samples(cand)
        return not any(_overlap(pts, self._world_samples(o), SAMPLE_MM) for o in others)

    def _world_samples(self, pose: Pose2) -> NDArray[np.float64]:
        a = math.radians(pose[2])
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return self._samples @ R.T + np.array(pose[:2])

    def _fits(self, cand: Pose2, placed: list[Pose2],
              area: AreaSpec) -> bool:
        pts = self._world_samples(cand)
        if not (np.all((pts[:, 0] >= area.x_mm[0]) & (pts[:, 0] <= area.x_mm[1]))
                and np.all((pts[:, 1] >= area.y_mm[0]) & (pts[:, 1] <= area.y_mm[1]))):
            return False
        reach = 2 * self.spec.part_radius_mm()
        clear = self.spec.scatter.clear_part
        for k, other in enumerate(placed):
            margin = clear.clearance_mm if (k == 0 and clear is not None) else SAMPLE_MM
            d = math.hypot(cand[0] - other[0], cand[1] - other[1])
            if d > reach + margin:
                continue
            if d < self.spec.part_radius_mm() / 2:
                return False  # nearly on top of each other: the edges may not cross
            if _overlap(pts, self._world_samples(other), margin):
                return False
        return True

    def _slide(self, cand: Pose2, placed: list[Pose2], area: AreaSpec,
               rng: np.random.Generator) -> Pose2:
        """Slide the part toward a random direction until it touches a neighbour or the area's edge."""
        a = rng.uniform(0, 2 * math.pi)
        step = np.array([math.cos(a), math.sin(a)]) * SAMPLE_MM
        cur = cand
        for _ in range(400):
            nxt = (cur[0] + float(step[0]), cur[1] + float(step[1]), cur[2])
            if not self._fits(nxt, placed, area):
                return cur
            cur = nxt
        return cur


def _sample_points(outline_mm: list[list[float]], holes_mm: list[list[list[float]]]) -> NDArray[np.float64]:
    """Points along the outline every SAMPLE_MM, part frame, mm (two outlines of one part overlap
    only where their edges cross or come near: neither fits inside the other)."""
    poly = np.asarray(outline_mm, dtype=np.float64)
    edge = []
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        n = max(1, int(math.ceil(float(np.linalg.norm(q - p)) / SAMPLE_MM)))
        edge.append(p + (q - p) * (np.arange(n)[:, None] / n))
    return np.concatenate(edge)


def _overlap(a: NDArray[np.float64], b: NDArray[np.float64], margin_mm: float) -> bool:
    """True when two sampled parts come nearer than ``margin_mm`` (point to point)."""
    lo = np.maximum(a.min(axis=0), b.min(axis=0)) - margin_mm
    hi = np.minimum(a.max(axis=0), b.max(axis=0)) + margin_mm
    if np.any(lo > hi):
        return False
    a = a[np.all((a >= lo) & (a <= hi), axis=1)]
    b = b[np.all((b >= lo) & (b <= hi), axis=1)]
    if len(a) == 0 or len(b) == 0:
        return False
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)
    return bool(d2.min() < margin_mm * margin_mm)
