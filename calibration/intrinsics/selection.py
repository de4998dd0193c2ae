"""Choosing the lens model and board warp of an intrinsics calibration by k-fold cross-validation
(``crossval``), not by the RMS: ``select_by_cross_validation``.

Every candidate is calibrated on all views and cross-validated over the same partitions of them
(``crossval.PartitionRun``); a richer candidate must beat every simpler one by ``SELECT_MARGIN``. With
``repeats="auto"`` the candidates draw partitions jointly until every comparison the rule makes is decided
beyond the two medians' 90 % intervals (``crossval.median_half_width``); a candidate a simpler one beats by
the margin beyond both intervals cannot be chosen and stops drawing. Lengths in pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from calibration.intrinsics.crossval import (
    CV_CONFIDENCE,
    CV_MIN_REPEATS,
    CV_REPEATS,
    SELECT_MARGIN,
    PartitionRun,
    Repeats,
    check_repeats,
    median_half_width,
    most_partitions,
)
from calibration.intrinsics.results import CrossValidationError, IntrinsicsError, IntrinsicsResult
from calibration.intrinsics.solver import calibrate
from calibration.observations import Detection
from calibration.targets import Target

Candidate = tuple[str, bool] | tuple[str, bool, bool]
"""A candidate of ``select_by_cross_validation``: ``(model, board_warp)`` or ``(model, board_warp, regularise)``."""


def select_by_cross_validation(detections: Sequence[Detection], target: Target,
                               candidates: Sequence[Candidate], k: int = 2, *,
                               image_size: tuple[int, int] | None = None,
                               drop_outliers: bool = False, reject_views: bool = False,
                               repeats: Repeats = "auto") -> tuple[IntrinsicsResult, dict[str, Any]]:
    """Choose the lens model and board warp by k-fold cross-validation, not by the RMS (a richer
    model always lowers the RMS; only data it has not seen can say whether it describes the lens).

    ``candidates``: ``(model, board_warp)`` pairs, or ``(model, board_warp, regularise)`` (``calibrate``'s
    regularised solve, mrcal's rule), simplest first. Each is calibrated on all views
    and cross-validated over the same partitions (``cross_validate``; every candidate on the same
    partitions of the same views when their full solves keep the same views); a candidate that
    cannot be (folds do not solve in half the partitions or more, too few views) is refused with
    the reason. The chosen one has the smallest median projection difference between its folds,
    where a richer candidate must beat every simpler one by ``SELECT_MARGIN``.

    ``repeats``: a fixed count of partitions, or ``"auto"`` (default), a sequential rule over the
    candidates jointly (every candidate draws the same partitions, so where the drawing stopped
    cannot favour one): draw ``CV_MIN_REPEATS`` (3) partitions, then one more at a time until the
    choice is settled, at most ``CV_REPEATS`` (8). Settled: every comparison the rule makes (a
    candidate's median against ``1 - SELECT_MARGIN`` times the best simpler one's) is decided beyond
    the two medians' 90 % intervals combined (``median_half_width``, relative, in quadrature), and no
    candidate has some but not all of its partitions failed (a candidate whose every partition failed
    is refused). Returns the chosen calibration and ``{"k", "repeats", "repeats_rule", "chosen",
    "candidates", "cross_validation", "rule"}``; raises CrossValidationError when no candidate can
    be cross-validated.

    ``reject_views``: each candidate's full calibration removes its influential views
    (``calibrate(reject_views=True)``; not the splined model's solver) and its folds are made of the
    views it kept.
    """
    check_repeats(repeats)
    rows: list[dict[str, Any]] = []
    runs: list[PartitionRun | None] = []
    for cand in candidates:
        model, warp, reg = cand[0], bool(cand[1]), bool(cand[2]) if len(cand) > 2 else False
        row: dict[str, Any] = {"model": model, "board_warp": warp}
        if reg:
            row["regularised"] = True
        try:
            full = calibrate(detections, target, model, image_size=image_size, drop_outliers=drop_outliers,
                             board_warp=warp, reject_views=reject_views and model != "splined", regularise=reg)
            runs.append(PartitionRun(detections, target, model, k, image_size, drop_outliers, full, warp,
                                     most_partitions(repeats), reg))
        except IntrinsicsError as exc:
            row["refused"] = str(exc)
            runs.append(None)
        rows.append(row)
    live = [r for r in runs if r is not None]
    for _ in range(CV_MIN_REPEATS if repeats == "auto" else int(repeats)):
        for run in live:
            run.draw()
    if repeats == "auto":
        out: set[int] = set()          # candidates that cannot be chosen: they draw no more
        while True:
            out |= _out_of_the_race(live)
            drawing = [r for i, r in enumerate(live) if i not in out and len(r.parts) < CV_REPEATS]
            if not drawing or _settled([r for i, r in enumerate(live) if i not in out]):
                break
            for run in drawing:
                run.draw()
    drawn = max((len(r.parts) for r in live), default=0)
    rule = ("fixed" if repeats != "auto" else
            f"auto: until the choice is settled beyond the medians' {CV_CONFIDENCE:.0%} intervals, "
            f"{CV_MIN_REPEATS}-{CV_REPEATS} partitions")
    results: list[tuple[IntrinsicsResult, dict[str, Any]] | None] = []
    for row, done in zip(rows, runs, strict=True):
        if done is None:
            results.append(None)
            continue
        try:
            cv = done.summary(rule)
        except IntrinsicsError as exc:
            row["refused"] = str(exc)
            results.append(None)
            continue
        full = done.full
        row.update({"rms_px": full.rms_px, "cross_validation_px": cv["projection_difference_rms_px"],
                    "cross_validation_spread_px": cv["spread_px"], "expected_px": cv["expected_from_uncertainty_px"],
                    "cross_validation_interval_px": cv["median_interval_px"], "partitions": cv["repeats"]})
        if cv["failed"]:
            row["partitions_failed"] = len(cv["failed"])
        if full.view_rejection is not None:
            row["views_rejected"] = [r["image"] for r in full.view_rejection["rejected"]]
        results.append((full, cv))
    best: int | None = None
    chosen: tuple[IntrinsicsResult, dict[str, Any]] | None = None
    for i, r in enumerate(results):
        if r is not None and (chosen is None or r[1]["projection_difference_rms_px"]
                              < (1.0 - SELECT_MARGIN) * chosen[1]["projection_difference_rms_px"]):
            best, chosen = i, r
    if best is None or chosen is None:
        raise CrossValidationError("no candidate model could be cross-validated: "
                                   + "; ".join(f"{c['model']}{' + board warp' if c['board_warp'] else ''}: "
                                               f"{c['refused']}" for c in rows))
    for i, row in enumerate(rows):
        row["chosen"] = i == best
    how = ("" if repeats != "auto" else
           f" (drawn until the choice was settled beyond the medians' {CV_CONFIDENCE:.0%} intervals, "
           f"{CV_MIN_REPEATS}-{CV_REPEATS})")
    return chosen[0], {"k": k, "repeats": drawn, "repeats_rule": rule,
                       "chosen": {"model": rows[best]["model"], "board_warp": rows[best]["board_warp"],
                                  **({"regularised": True} if rows[best].get("regularised") else {})},
                       "candidates": rows, "cross_validation": chosen[1],
                       "rule": f"smallest median {k}-fold projection difference over the covered region, over "
                               f"{drawn} partitions of the views{how}; a richer candidate must beat a simpler "
                               f"one by {SELECT_MARGIN:.0%}"}


def _interval(run: PartitionRun) -> tuple[float, float] | None:
    """(log median, log half-width) of a run whose partitions all solved, else None."""
    per = run.per()
    if not all(math.isfinite(v) for v in per):
        return None
    return math.log(float(np.median(per))), median_half_width(per)


def _out_of_the_race(runs: Sequence[PartitionRun]) -> set[int]:
    """Indices of the runs that cannot be chosen whatever more partitions give: every partition
    failed (refused), or a simpler run's median beats theirs by more than ``SELECT_MARGIN`` beyond
    both 90 % intervals (upper end of the simpler one's < (1 - margin) x lower end of theirs). Such a
    run never becomes the best in the selection's pass either (the best it meets is at most the
    simpler one's median / (1 - margin)), so its median does not change the choice."""
    out = {i for i, r in enumerate(runs) if r.all_failed()}
    iv = [_interval(r) for r in runs]
    for i, a in enumerate(iv):
        if a is None or i in out:
            continue
        for b in iv[:i]:
            if b is not None and b[0] + b[1] < math.log1p(-SELECT_MARGIN) + a[0] - a[1]:
                out.add(i)
                break
    return out


def _settled(runs: Sequence[PartitionRun]) -> bool:
    """Whether the choice among ``runs`` (same partitions drawn) is settled: the selection's
    comparisons, replayed on the current medians, are each decided beyond the 90 % intervals."""
    best: tuple[float, float] | None = None           # (log median, log half-width) of the best so far
    for run in runs:
        if run.all_failed():
            continue                                   # refused whatever follows
        iv = _interval(run)
        if iv is None:
            return False                               # some failed: only more partitions can say
        m, h = iv
        if best is None:
            best = (m, h)
            continue
        gap = m - (math.log1p(-SELECT_MARGIN) + best[0])
        if abs(gap) < math.hypot(h, best[1]):
            return False
        if gap < 0:
            best = (m, h)
    return True
