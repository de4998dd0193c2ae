"""Discrete tracking of the top level's candidates down the pyramid (``search.find``'s step 2).

On the level below the top, +-2 angle steps and +-2 px on spread responses, climbing on from the
window's edge (``climb``); +-1 on each finer level; on the last discrete level a second pass on
unspread responses settles the +-1 px plateaus. A model without a level below its top settles its
candidates on the top level's unspread responses (``settle_top``). Own code over
``responses.track`` (the compiled gathers).
"""

from __future__ import annotations

import math
import time

import numpy as np
from numpy.typing import NDArray

from vision.image import F64, U8
from vision.shape.model import LevelModel, ShapeModel
from vision.shape.refine import Pose
from vision.shape.responses import response_maps, spread_max, track

HYPOTHESES_PER_POSITION = 3
TRACK_BATCH = 160
"""Candidates tracked per compiled call (the top level's most, ``top_search.MAX_TOP_CANDIDATES``, in one): each
call and each climbing step of a batch costs ~50 us of Python around the kernel (batches of 32 were 4-5
times that per image); the search's clock is read between batches."""


class Clock:
    """A search's time: the wall-clock deadline of ``timeout_s`` (None: none), elapsed wall and CPU s."""

    def __init__(self, timeout_s: float | None) -> None:
        self.c0 = time.process_time()
        self.t0 = time.perf_counter()
        self.deadline = None if timeout_s is None else self.t0 + timeout_s

    def expired(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def cpu(self) -> float:
        return time.process_time() - self.c0


def nms_pose(poses: list[Pose], dist: float, dtheta: float) -> list[Pose]:
    """Drop poses within ``dist`` and ``dtheta`` of a better one (poses sorted best first)."""
    if len(poses) < 2:
        return poses
    P = np.array([[p.x, p.y, p.theta] for p in poses])
    dd = (P[:, None, 0] - P[None, :, 0]) ** 2 + (P[:, None, 1] - P[None, :, 1]) ** 2
    da = np.abs(np.mod(P[:, None, 2] - P[None, :, 2] + math.pi, 2 * math.pi) - math.pi)
    close = (dd <= dist * dist) & (da <= dtheta)
    keep = np.ones(len(poses), bool)
    for i in range(len(poses)):
        if keep[i]:
            keep[i + 1:] &= ~close[i, i + 1:]
    return [p for p, k in zip(poses, keep, strict=True) if k]


def track_down(model: ShapeModel, pyr: list[U8], thr_grad: float, cands: list[Pose],
                lowest_discrete: int, coarse_min: float, clock: Clock) -> tuple[list[Pose], bool]:
    """Discrete tracking from the level below the top down to ``lowest_discrete``."""
    L = model.top_level
    timed_out = False
    if lowest_discrete == L and cands:
        return settle_top(model, pyr[L], thr_grad, cands, coarse_min), False
    for lv in range(L - 1, lowest_discrete - 1, -1):
        if not cands:
            break
        lm = model.levels[lv]
        last = lv == lowest_discrete
        first = lv == L - 1
        raw = response_maps(pyr[lv], thr_grad, spread=1)
        spread_ = spread_max(raw, 3)
        P = np.array([(c.x, c.y, c.theta, c.scale) for c in cands], dtype=np.float64)
        # plateau centres: *2, rounded half to even (as Python's round)
        cx = np.rint(P[:, 0] * 2).astype(np.int64)
        cy = np.rint(P[:, 1] * 2).astype(np.int64)
        th = np.ascontiguousarray(P[:, 2])
        ks = np.ascontiguousarray(P[:, 3])
        nxt: list[Pose] = []
        for start in range(0, len(cands), TRACK_BATCH):
            sl = slice(start, start + TRACK_BATCH)
            k_ = ks[sl]
            # below the top level the angle and position are still coarse: +-2 steps and +-2 px
            # (+-3 with the spread) there, +-1 further down
            if first:
                xs_, ys_, ts_, sc_ = climb(spread_, lm, cx[sl], cy[sl], th[sl], 2, k_)
            else:
                xs_, ys_, ts_, sc_ = track(spread_, lm, cx[sl], cy[sl], th[sl], 1, 1, k_)
            if last:
                # the spread responses leave +-1 px plateaus: settle on the unspread ones
                keep = sc_ >= coarse_min * 0.7
                xs_, ys_, ts_, k_ = xs_[keep], ys_[keep], ts_[keep], k_[keep]
                xs_, ys_, ts_, sc_ = track(raw, lm, np.rint(xs_).astype(np.int64),
                                           np.rint(ys_).astype(np.int64), ts_, 1, 1, k_)
            bar = coarse_min * (0.6 if last else 0.8)
            nxt += [Pose(a, b_, t_, c_, kk)  # Python floats from tolist(): no numpy scalar per value
                    for a, b_, t_, c_, kk in zip(xs_.tolist(), ys_.tolist(), ts_.tolist(), sc_.tolist(), k_.tolist(),
                                                 strict=True) if c_ >= bar]
            if clock.expired():
                timed_out = True
                break
        nxt.sort(key=lambda p: -p.score)
        cands = nms_pose(nxt, 2.0, 2.5 * lm.angle_step)
        if timed_out:
            break
    return cands, timed_out


def settle_top(model: ShapeModel, top_img: U8, thr_grad: float, cands: list[Pose], coarse_min: float) -> list[Pose]:
    """A small model has no level to track on below its top: its candidates (spread scores, +-1 px
    plateaus) are settled on the top level's unspread responses and held to the last tracking
    level's minimum, so that only those go on to the (costlier) least-squares stage."""
    lm = model.levels[model.top_level]
    raw = response_maps(top_img, thr_grad, spread=1)
    xs, ys, ts, sc = track(raw, lm, np.array([int(round(c.x)) for c in cands], dtype=np.int64),
                           np.array([int(round(c.y)) for c in cands], dtype=np.int64),
                           np.array([c.theta for c in cands]), 1, 1, np.array([c.scale for c in cands]))
    out = [Pose(float(x), float(y), float(t), c.score, c.scale)
           for x, y, t, v, c in zip(xs, ys, ts, sc, cands, strict=True) if v >= coarse_min * 0.6]
    return nms_pose(out, 2.0, 2.5 * lm.angle_step)


CLIMB_STEPS = 4
"""Most +-1 px steps a tracked candidate whose best lies on its window's edge climbs on (``climb``)."""


def climb(resp: U8, lm: LevelModel, cx: NDArray[np.int64], cy: NDArray[np.int64], th: F64, reach: int,
           k: F64) -> tuple[F64, F64, F64, F64]:
    """``track`` over +-``reach`` px and angle steps; a candidate whose best lies on the window's
    edge then climbs on, +-1 px and step at a time, while its score rises (``CLIMB_STEPS`` at most):
    the coarse level's peak of a partly hidden part can sit a few pixels along its visible edges
    from the true pose (the edges that remain match along a ridge), beyond one window."""
    xs, ys, ts, sc = track(resp, lm, cx, cy, th, reach, reach, k)
    da = np.abs(np.mod(ts - th + math.pi, 2 * math.pi) - math.pi)
    moving = np.flatnonzero((np.abs(xs - cx) >= reach - 0.5) | (np.abs(ys - cy) >= reach - 0.5)
                            | (da >= (reach - 0.5) * lm.angle_step))
    for _ in range(CLIMB_STEPS):
        if len(moving) == 0:
            break
        x0, y0, t0 = np.rint(xs[moving]).astype(np.int64), np.rint(ys[moving]).astype(np.int64), ts[moving]
        x2, y2, t2, s2 = track(resp, lm, x0, y0, t0, 1, 1, k[moving])
        rose = s2 > sc[moving]
        j = moving[rose]
        xs[j], ys[j], ts[j], sc[j] = x2[rose], y2[rose], t2[rose], s2[rose]
        moving = j
    return xs, ys, ts, sc


def few_per_position(cands: list[Pose], radius: float) -> list[Pose]:
    """At most a few angle hypotheses per position go on to the (costlier) least-squares stage."""
    per_pos: list[list[Pose]] = []
    r_pos = radius ** 2
    for c in sorted(cands, key=lambda p: -p.score):
        for grp in per_pos:
            if (grp[0].x - c.x) ** 2 + (grp[0].y - c.y) ** 2 < r_pos:
                if len(grp) < HYPOTHESES_PER_POSITION and c.score >= 0.8 * grp[0].score:
                    grp.append(c)
                break
        else:
            per_pos.append([c])
    return [c for grp in per_pos for c in grp]
