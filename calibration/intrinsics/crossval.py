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


def cross_validate(detections: Sequence[Detection], target: Target, model: str, k: int = 2, *,
                   image_size: tuple[int, int] | None = None, drop_outliers: bool = False,
                   full: IntrinsicsResult | None = None, board_warp: bool = False) -> dict[str, Any]:
    """k-fold cross-validation (mrcal's idea): split the views into ``k`` disjoint folds
    (view ``i`` goes to fold ``i mod k``), calibrate each fold on its own, and report the
    projection difference between every pair of fold solutions over the image region the whole
    data set covered (best rotation compensated). Two solutions from independent data differ by
    about sqrt(2) times each one's projection uncertainty if the model fits the lens; a much
    larger difference means the model cannot describe the lens (or the data are inconsistent).

    Folds are made of the views the full calibration used (``full`` if given); ``board_warp``
    solves each fold with the target's warp (``calibrate``). Raises
    CrossValidationError (the calibration itself is not affected) when ``k`` is too large for
    the usable views or a fold cannot be calibrated.
    """
    if k < 2:
        raise IntrinsicsError("cross-validation needs k >= 2 folds")
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
    fold_res = []
    for f in range(k):
        try:
            fold_res.append(calibrate(usable[f::k], target, model, image_size=full.camera.size,
                                      drop_outliers=drop_outliers, board_warp=board_warp, spline_grid=grid))
        except IntrinsicsError as exc:
            raise CrossValidationError(f"fold {f + 1} of {k} ({len(usable[f::k])} views) cannot be calibrated "
                                       f"({exc}); use a smaller k") from exc
    pairs = []
    for a in range(k):
        for b in range(a + 1, k):
            d = projection_difference(fold_res[a].camera, fold_res[b].camera, pts)
            pairs.append({"folds": [a, b], "rms_px": d["rms_px"], "max_px": d["max_px"]})
    rms = [pp["rms_px"] for pp in pairs]
    return {
        "k": k,
        "folds": [{"views": int(sum(v.used for v in r.views)), "rms_px": r.rms_px,
                   "projection_uncertainty_px": r.uncertainty["projection_rms_px"]} for r in fold_res],
        "pairs": pairs,
        "projection_difference_rms_px": float(np.mean(rms)),
        "projection_difference_max_px": float(np.max([pp["max_px"] for pp in pairs])),
        "expected_from_uncertainty_px": float(np.mean([
            np.hypot(fold_res[p["folds"][0]].uncertainty["projection_rms_px"] or 0.0,
                     fold_res[p["folds"][1]].uncertainty["projection_rms_px"] or 0.0) for p in pairs])),
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
                               drop_outliers: bool = False, reject_views: bool = False
                               ) -> tuple[IntrinsicsResult, dict[str, Any]]:
    """Choose the lens model and board warp by k-fold cross-validation, not by the RMS (a richer
    model always lowers the RMS; only data it has not seen can say whether it describes the lens).

    ``candidates``: ``(model, board_warp)`` pairs, simplest first. Each is calibrated on all views
    and cross-validated (``cross_validate``); a candidate that cannot be (a fold does not solve,
    too few views) is refused with the reason. The chosen one has the smallest projection
    difference between its folds, where a richer candidate must beat every simpler one by
    ``SELECT_MARGIN``. Returns the chosen calibration and ``{"chosen", "candidates", "rule"}``;
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
                                full=full, board_warp=warp)
        except IntrinsicsError as exc:
            row["refused"] = str(exc)
            rows.append(row)
            results.append(None)
            continue
        row.update({"rms_px": full.rms_px, "cross_validation_px": cv["projection_difference_rms_px"],
                    "expected_px": cv["expected_from_uncertainty_px"]})
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
    return chosen[0], {"k": k, "chosen": {"model": rows[best]["model"], "board_warp": rows[best]["board_warp"]},
                       "candidates": rows, "cross_validation": chosen[1],
                       "rule": f"smallest {k}-fold projection difference over the covered region; a richer "
                               f"candidate must beat a simpler one by {SELECT_MARGIN:.0%}"}
