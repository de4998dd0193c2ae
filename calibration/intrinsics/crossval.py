"""k-fold cross-validation of an intrinsics calibration (mrcal's idea)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from calibration.intrinsics.results import MIN_VIEWS, CrossValidationError, IntrinsicsError, IntrinsicsResult
from calibration.intrinsics.solver import calibrate
from calibration.intrinsics.uncertainty import (
    covered_points,
    projection_difference,
)
from calibration.observations import Detection
from calibration.targets import Target

CV_REPEATS = 8
"""Splits of the views cross-validation draws by default (``repeats``): the first is view ``i`` in fold
``i mod k``, the others seeded random partitions. One split of a dozen views is one draw of a statistic
that scatters several-fold between splits (OpenCV's 13-view right set: 0.15-0.85 px between halvings);
the median over eight is what the choice and the verdict use. Cost: ``k * repeats`` fold solves per
candidate (a 13-view set's eight candidates: a few CPU seconds)."""

CV_SEED = 2039
"""The random partitions' seed (fixed: the same data give the same choice)."""


def fold_partitions(n: int, k: int, repeats: int = CV_REPEATS, seed: int = CV_SEED) -> list[list[np.ndarray]]:
    """``repeats`` partitions of ``n`` views into ``k`` folds (index arrays): view ``i`` in fold ``i mod k``
    first, then seeded random partitions (each fold sorted, sizes as even as ``n`` allows)."""
    out = [[np.arange(f, n, k) for f in range(k)]]
    rng = np.random.default_rng(seed)
    for _ in range(repeats - 1):
        p = rng.permutation(n)
        out.append([np.sort(p[f::k]) for f in range(k)])
    return out


def cross_validate(detections: Sequence[Detection], target: Target, model: str, k: int = 2, *,
                   image_size: tuple[int, int] | None = None, drop_outliers: bool = False,
                   full: IntrinsicsResult | None = None, board_warp: bool = False,
                   repeats: int = CV_REPEATS) -> dict[str, Any]:
    """Repeated k-fold cross-validation (mrcal's idea, over several splits): split the views into ``k``
    disjoint folds, calibrate each fold on its own, and take the projection difference between every
    pair of fold solutions over the image region the whole data set covered (best rotation
    compensated); do so for ``repeats`` partitions (``fold_partitions``: view ``i`` in fold ``i mod k``,
    then seeded random ones) and report the **median** over them. Two solutions from independent data
    differ by about sqrt(2) times each one's projection uncertainty if the model fits the lens; a much
    larger difference means the model cannot describe the lens (or the data are inconsistent).

    Folds are made of the views the full calibration used (``full`` if given); ``board_warp``
    solves each fold with the target's warp (``calibrate``). A partition with a fold that cannot be
    calibrated counts as an infinite difference (listed in ``failed``): the data cannot carry the
    model there. Raises CrossValidationError (the calibration itself is not affected) when ``k`` is
    too large for the usable views, or when half the partitions or more fail (the median is then
    infinite: the data cannot carry the model).

    Returns ``k``, ``repeats``, ``folds`` and ``pairs`` (the first partition's),
    ``projection_difference_rms_px`` / ``_max_px`` / ``expected_from_uncertainty_px`` (medians over
    the partitions), ``per_partition_rms_px`` (None where one failed), ``spread_px`` (its 10 % and
    90 % quantiles over the partitions that solved) and ``failed``.
    """
    if k < 2:
        raise IntrinsicsError("cross-validation needs k >= 2 folds")
    if repeats < 1:
        raise IntrinsicsError("cross-validation needs repeats >= 1 partitions")
    found = [d for d in detections if d.found]
    if full is None:
        if len(found) < MIN_VIEWS * k:  # before spending a full calibration on it
            raise CrossValidationError(_too_large(k, len(found), "views with the target"))
        full = calibrate(found, target, model, image_size=image_size, drop_outliers=drop_outliers,
                         board_warp=board_warp)
    used = {v.image for v in full.views if v.used}
    usable = [d for d in found if d.image in used]
    if len(usable) < MIN_VIEWS * k:
        raise CrossValidationError(_too_large(k, len(usable), "usable views (after the full calibration's "
                                                              "rejections)"))
    pts = covered_points(full)
    grid = None
    if model == "splined":   # the folds use the full set's grid (one model, validated)
        lay = full.camera.dist
        grid = (int(lay[0]), int(lay[1]), float(lay[2]))
    parts: list[dict[str, Any] | None] = []
    failed: list[str] = []
    for r, folds in enumerate(fold_partitions(len(usable), k, repeats)):
        try:
            parts.append(_one_partition(usable, folds, target, model, pts, full, drop_outliers, board_warp, grid))
        except IntrinsicsError as exc:
            parts.append(None)
            failed.append(f"partition {r + 1}: fold of {len(folds[0])} views cannot be calibrated ({exc})")
    if 2 * len(failed) >= len(parts):
        raise CrossValidationError(f"{len(failed)} of {len(parts)} partitions into {k} folds cannot be "
                                   f"calibrated: the data cannot carry the {model} model ({failed[0]}); "
                                   "use a smaller k or add views")
    ok = [p for p in parts if p is not None]
    per = np.array([np.inf if p is None else p["rms"] for p in parts])
    first = next(p for p in parts if p is not None)
    spread = np.quantile([p["rms"] for p in ok], [0.1, 0.9])
    return {
        "k": k,
        "repeats": len(parts),
        "folds": first["folds"],
        "pairs": first["pairs"],
        "projection_difference_rms_px": float(np.median(per)),
        "projection_difference_max_px": float(np.median([np.inf if p is None else p["max"] for p in parts])),
        "expected_from_uncertainty_px": float(np.median([np.inf if p is None else p["expected"] for p in parts])),
        "per_partition_rms_px": [None if p is None else round(p["rms"], 6) for p in parts],
        "spread_px": [float(spread[0]), float(spread[1])],
        "failed": failed,
    }


def _one_partition(usable: list[Detection], folds: list[np.ndarray], target: Target, model: str, pts: np.ndarray,
                   full: IntrinsicsResult, drop_outliers: bool, board_warp: bool,
                   grid: tuple[int, int, float] | None) -> dict[str, Any]:
    """One partition's fold solutions and their pairwise projection differences (px)."""
    fold_res = [calibrate([usable[i] for i in f], target, model, image_size=full.camera.size,
                          drop_outliers=drop_outliers, board_warp=board_warp, spline_grid=grid) for f in folds]
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


def select_by_cross_validation(detections: Sequence[Detection], target: Target,
                               candidates: Sequence[tuple[str, bool]], k: int = 2, *,
                               image_size: tuple[int, int] | None = None,
                               drop_outliers: bool = False, reject_views: bool = False,
                               repeats: int = CV_REPEATS) -> tuple[IntrinsicsResult, dict[str, Any]]:
    """Choose the lens model and board warp by k-fold cross-validation, not by the RMS (a richer
    model always lowers the RMS; only data it has not seen can say whether it describes the lens).

    ``candidates``: ``(model, board_warp)`` pairs, simplest first. Each is calibrated on all views
    and cross-validated over ``repeats`` partitions (``cross_validate``; every candidate on the same
    partitions of the same views when their full solves keep the same views); a candidate that
    cannot be (folds do not solve in half the partitions or more, too few views) is refused with
    the reason. The chosen one has the smallest median projection difference between its folds,
    where a richer candidate must beat every simpler one by ``SELECT_MARGIN``. Returns the chosen
    calibration and ``{"k", "repeats", "chosen", "candidates", "cross_validation", "rule"}``;
    raises CrossValidationError when no candidate can be cross-validated.

    ``reject_views``: each candidate's full calibration removes its influential views
    (``calibrate(reject_views=True)``; not the splined model's solver) and its folds are made of the
    views it kept.
    """
    rows: list[dict[str, Any]] = []
    results: list[tuple[IntrinsicsResult, dict[str, Any]] | None] = []
    for model, warp in candidates:
        row: dict[str, Any] = {"model": model, "board_warp": warp}
        try:
            full = calibrate(detections, target, model, image_size=image_size, drop_outliers=drop_outliers,
                             board_warp=warp, reject_views=reject_views and model != "splined")
            cv = cross_validate(detections, target, model, k, image_size=image_size, drop_outliers=drop_outliers,
                                full=full, board_warp=warp, repeats=repeats)
        except IntrinsicsError as exc:
            row["refused"] = str(exc)
            rows.append(row)
            results.append(None)
            continue
        row.update({"rms_px": full.rms_px, "cross_validation_px": cv["projection_difference_rms_px"],
                    "cross_validation_spread_px": cv["spread_px"], "expected_px": cv["expected_from_uncertainty_px"]})
        if cv["failed"]:
            row["partitions_failed"] = len(cv["failed"])
        if full.view_rejection is not None:
            row["views_rejected"] = [r["image"] for r in full.view_rejection["rejected"]]
        rows.append(row)
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
    return chosen[0], {"k": k, "repeats": repeats,
                       "chosen": {"model": rows[best]["model"], "board_warp": rows[best]["board_warp"]},
                       "candidates": rows, "cross_validation": chosen[1],
                       "rule": f"smallest median {k}-fold projection difference over the covered region, over "
                               f"{repeats} partitions of the views; a richer candidate must beat a simpler one "
                               f"by {SELECT_MARGIN:.0%}"}
