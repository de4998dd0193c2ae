"""k-fold cross-validation of an intrinsics calibration (mrcal's idea), over several partitions of the
views, and choosing the lens model and board warp by it.

How many partitions (``repeats``): a fixed count, or ``"auto"`` (the default), a sequential rule.
Draw ``CV_MIN_REPEATS`` (3), then one more at a time, at most ``CV_REPEATS`` (8), until the
medians are known well enough. A median's uncertainty is its 90 % interval from the partitions'
own scatter (``median_half_width``: sqrt(pi/2) s / sqrt(n) with ``s`` the standard deviation of the
log differences, times Student's t, n - 1 degrees of freedom).
- One model (``cross_validate``): until the interval is within +-``SELECT_MARGIN`` (10 %).
- Choosing (``selection.select_by_cross_validation``), over the candidates jointly: every candidate
  draws the same partitions, until every comparison the rule makes is decided beyond the two
  intervals. A candidate a simpler one beats by the margin beyond both intervals cannot be chosen and
  stops drawing; this does not change the choice (it never becomes the best in the selection's pass).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from scipy.stats import t as student_t

from calibration.intrinsics.results import MIN_VIEWS, CrossValidationError, IntrinsicsError, IntrinsicsResult
from calibration.intrinsics.solver import calibrate
from calibration.intrinsics.uncertainty import (
    covered_points,
    projection_difference,
)
from calibration.observations import Detection
from calibration.targets import Target

CV_REPEATS = 8
"""The most partitions of the views cross-validation draws (``repeats="auto"``, the default) and what
it drew before the rule below: the first is view ``i`` in fold ``i mod k``, the others seeded random
partitions. One split of a dozen views is one draw of a statistic that scatters several-fold between
splits (OpenCV's 13-view right set: 0.15-0.85 px between halvings); the median over the partitions is
what the choice and the verdict use. Cost: ``k`` fold solves per partition and candidate."""

CV_MIN_REPEATS = 3
"""The fewest partitions the automatic rule draws (the median of fewer is one split's luck)."""

CV_CONFIDENCE = 0.90
"""Two-sided confidence of the median's interval that the automatic rule uses (``median_interval``)."""

CV_SEED = 2039
"""The random partitions' seed (fixed: the same data give the same choice)."""

Repeats = int | Literal["auto"]
"""``repeats`` of cross-validation: a fixed count of partitions, or ``"auto"`` (the sequential rule)."""


def median_half_width(values: Sequence[float] | np.ndarray, confidence: float = CV_CONFIDENCE) -> float:
    """Half-width, in log units (relative), of the ``confidence`` interval of the median of
    ``values`` (projection differences, px, one per partition): the sample median's standard error
    sqrt(pi/2) * s / sqrt(n) with ``s`` the standard deviation of log(values) (a log-normal scatter:
    the statistic is a positive ratio-like length), times Student's t with n - 1 degrees of freedom
    (``s`` is itself estimated from n values). Infinite for fewer than 2 values or a failed
    (infinite or non-positive) one: a failure can only be outweighed by more partitions."""
    v = np.asarray(values, dtype=float)
    if v.size < 2 or not np.all(np.isfinite(v)) or np.any(v <= 0):
        return math.inf
    sd = float(np.std(np.log(v), ddof=1))
    return float(student_t.ppf(0.5 + confidence / 2, v.size - 1)) * math.sqrt(math.pi / 2) * sd / math.sqrt(v.size)


def fold_partitions(n: int, k: int, repeats: int = CV_REPEATS, seed: int = CV_SEED) -> list[list[np.ndarray]]:
    """``repeats`` partitions of ``n`` views into ``k`` folds (index arrays): view ``i`` in fold ``i mod k``
    first, then seeded random partitions (each fold sorted, sizes as even as ``n`` allows). The first
    ``r`` of ``repeats`` partitions are ``fold_partitions(n, k, r)``."""
    out = [[np.arange(f, n, k) for f in range(k)]]
    rng = np.random.default_rng(seed)
    for _ in range(repeats - 1):
        p = rng.permutation(n)
        out.append([np.sort(p[f::k]) for f in range(k)])
    return out


def check_repeats(repeats: Repeats) -> None:
    """Raise IntrinsicsError unless ``repeats`` is ``"auto"`` or a count >= 1."""
    if repeats == "auto":
        return
    if isinstance(repeats, bool) or not isinstance(repeats, int):
        raise IntrinsicsError(f"cross-validation repeats must be a count >= 1 or 'auto', not {repeats!r}")
    if repeats < 1:
        raise IntrinsicsError("cross-validation needs repeats >= 1 partitions")


class PartitionRun:
    """One candidate's cross-validation, drawn one partition at a time (``draw``)."""

    def __init__(self, detections: Sequence[Detection], target: Target, model: str, k: int,
                 image_size: tuple[int, int] | None, drop_outliers: bool, full: IntrinsicsResult | None,
                 board_warp: bool, most: int, regularise: bool = False) -> None:
        if k < 2:
            raise IntrinsicsError("cross-validation needs k >= 2 folds")
        found = [d for d in detections if d.found]
        if full is None:
            if len(found) < MIN_VIEWS * k:  # before spending a full calibration on it
                raise CrossValidationError(_too_large(k, len(found), "views with the target"))
            full = calibrate(found, target, model, image_size=image_size, drop_outliers=drop_outliers,
                             board_warp=board_warp, regularise=regularise)
        used = {v.image for v in full.views if v.used}
        self.usable = [d for d in found if d.image in used]
        if len(self.usable) < MIN_VIEWS * k:
            raise CrossValidationError(_too_large(k, len(self.usable), "usable views (after the full calibration's "
                                                                       "rejections)"))
        self.k, self.model, self.target, self.full = k, model, target, full
        self.drop_outliers, self.board_warp, self.regularise = drop_outliers, board_warp, regularise
        self.pts = covered_points(full)
        self.grid = None
        if model == "splined":   # the folds use the full set's grid (one model, validated)
            lay = full.camera.dist
            self.grid = (int(lay[0]), int(lay[1]), float(lay[2]))
        self.partitions = fold_partitions(len(self.usable), k, most)
        self.parts: list[dict[str, Any] | None] = []
        self.failed: list[str] = []

    def draw(self) -> None:
        """Solve the next partition's folds."""
        r = len(self.parts)
        folds = self.partitions[r]
        try:
            self.parts.append(_one_partition(self.usable, folds, self.target, self.model, self.pts, self.full,
                                             self.drop_outliers, self.board_warp, self.grid, self.regularise))
        except IntrinsicsError as exc:
            self.parts.append(None)
            self.failed.append(f"partition {r + 1}: fold of {len(folds[0])} views cannot be calibrated ({exc})")

    def per(self) -> list[float]:
        return [math.inf if p is None else p["rms"] for p in self.parts]

    def all_failed(self) -> bool:
        return len(self.failed) == len(self.parts)

    def summary(self, rule: str) -> dict[str, Any]:
        """The cross-validation block (``cross_validate``'s return); raises CrossValidationError when
        half the partitions or more failed."""
        parts, failed, k = self.parts, self.failed, self.k
        if 2 * len(failed) >= len(parts):
            raise CrossValidationError(f"{len(failed)} of {len(parts)} partitions into {k} folds cannot be "
                                       f"calibrated: the data cannot carry the {self.model} model ({failed[0]}); "
                                       "use a smaller k or add views")
        ok = [p for p in parts if p is not None]
        per = np.array(self.per())
        first = next(p for p in parts if p is not None)
        spread = np.quantile([p["rms"] for p in ok], [0.1, 0.9])
        med = float(np.median(per))
        h = median_half_width(per)
        return {
            "k": k,
            "repeats": len(parts),
            "repeats_rule": rule,
            "folds": first["folds"],
            "pairs": first["pairs"],
            "projection_difference_rms_px": med,
            "projection_difference_max_px": float(np.median([np.inf if p is None else p["max"] for p in parts])),
            "expected_from_uncertainty_px": float(np.median([np.inf if p is None else p["expected"]
                                                             for p in parts])),
            "per_partition_rms_px": [None if p is None else round(p["rms"], 6) for p in parts],
            "spread_px": [float(spread[0]), float(spread[1])],
            "median_interval_px": ([med * math.exp(-h), med * math.exp(h)] if math.isfinite(h) else None),
            "failed": failed,
        }


def most_partitions(repeats: Repeats) -> int:
    """The most partitions ``repeats`` may draw (``CV_REPEATS`` for ``"auto"``)."""
    return CV_REPEATS if repeats == "auto" else int(repeats)


def cross_validate(detections: Sequence[Detection], target: Target, model: str, k: int = 2, *,
                   image_size: tuple[int, int] | None = None, drop_outliers: bool = False,
                   full: IntrinsicsResult | None = None, board_warp: bool = False,
                   repeats: Repeats = "auto", regularise: bool = False) -> dict[str, Any]:
    """Repeated k-fold cross-validation (mrcal's idea, over several splits): split the views into ``k``
    disjoint folds, calibrate each fold on its own, and take the projection difference between every
    pair of fold solutions over the image region the whole data set covered (best rotation
    compensated); do so for several partitions (``fold_partitions``: view ``i`` in fold ``i mod k``,
    then seeded random ones) and report the **median** over them. Two solutions from independent data
    differ by about sqrt(2) times each one's projection uncertainty if the model fits the lens; a much
    larger difference means the model cannot describe the lens (or the data are inconsistent).

    ``repeats``: a fixed count of partitions, or ``"auto"`` (default): draw ``CV_MIN_REPEATS`` (3),
    then one more at a time until the median's ``CV_CONFIDENCE`` (90 %) interval
    (``median_half_width``) lies within +-``SELECT_MARGIN`` (10 %) of it, at most ``CV_REPEATS`` (8).

    Folds are made of the views the full calibration used (``full`` if given); ``board_warp``
    solves each fold with the target's warp, ``regularise`` regularised (``calibrate``). A partition
    with a fold that cannot be calibrated counts as an infinite difference (listed in ``failed``): the
    data cannot carry the model there. Raises CrossValidationError (the calibration itself is not
    affected) when ``k`` is too large for the usable views, or when half the partitions or more fail (the median is then
    infinite: the data cannot carry the model).

    Returns ``k``, ``repeats`` (partitions drawn), ``repeats_rule``, ``folds`` and ``pairs`` (the
    first partition's), ``projection_difference_rms_px`` / ``_max_px`` /
    ``expected_from_uncertainty_px`` (medians over the partitions), ``per_partition_rms_px`` (None
    where one failed), ``spread_px`` (its 10 % and 90 % quantiles over the partitions that solved),
    ``median_interval_px`` (the median's 90 % interval; None when a partition failed) and ``failed``.
    """
    check_repeats(repeats)
    run = PartitionRun(detections, target, model, k, image_size, drop_outliers, full, board_warp,
                       most_partitions(repeats), regularise)
    if repeats != "auto":
        for _ in range(int(repeats)):
            run.draw()
        return run.summary("fixed")
    for _ in range(CV_MIN_REPEATS):
        run.draw()
    while len(run.parts) < CV_REPEATS and not (
            run.all_failed() or median_half_width(run.per()) <= math.log1p(SELECT_MARGIN)):
        run.draw()
    return run.summary(f"auto: until the median's {CV_CONFIDENCE:.0%} interval is within "
                       f"{SELECT_MARGIN:.0%}, {CV_MIN_REPEATS}-{CV_REPEATS} partitions")


def _one_partition(usable: list[Detection], folds: list[np.ndarray], target: Target, model: str, pts: np.ndarray,
                   full: IntrinsicsResult, drop_outliers: bool, board_warp: bool,
                   grid: tuple[int, int, float] | None, regularise: bool = False) -> dict[str, Any]:
    """One partition's fold solutions and their pairwise projection differences (px)."""
    fold_res = [calibrate([usable[i] for i in f], target, model, image_size=full.camera.size,
                          drop_outliers=drop_outliers, board_warp=board_warp, spline_grid=grid,
                          regularise=regularise) for f in folds]
    pairs = []
    for a in range(len(folds)):
        for b in range(a + 1, len(folds)):
            d = projection_difference(fold_res[a].camera, fold_res[b].camera, pts)
            pairs.append({"folds": [a, b], "rms_px": d["rms_px"], "max_px": d["max_px"]})
    unc = [r.uncertainty["projection_rms_px"] or 0.0 for r in fold_res]
    return {
        "folds": [{"views": int(sum(v.used for v in r.views)), "rms_px": r.rms_px,
                   "projection_uncertainty_px": r.uncertainty["projection_rms_px"]} for r in fold_res],
        "pairs": pairs,
        "rms": float(np.mean([pp["rms_px"] for pp in pairs])),
        "max": float(np.max([pp["max_px"] for pp in pairs])),
        "expected": float(np.mean([np.hypot(unc[p["folds"][0]], unc[p["folds"][1]]) for p in pairs])),
    }


def _too_large(k: int, n: int, what: str) -> str:
    hint = (f"use k <= {n // MIN_VIEWS}" if n // MIN_VIEWS >= 2
            else f"cross-validation needs at least {2 * MIN_VIEWS} usable views")
    return (f"k = {k} is too large for {n} views: {n} {what} are too few for {k}-fold cross-validation "
            f"(each fold needs at least {MIN_VIEWS}); {hint}")


SELECT_MARGIN = 0.1
"""A richer candidate is chosen only when its cross-validation difference is this much (10 %) below
the simpler one's: two halves of one set scatter, and a tie goes to fewer parameters."""
