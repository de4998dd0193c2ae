"""Cross-validation over repeated partitions of the views (issue 39): the median over several splits,
and a model the data cannot carry in half the partitions or more is refused."""

from __future__ import annotations

import functools
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest

import calibration.intrinsics.crossval as crossval
from calibration.camera_model import CameraModel
from calibration.intrinsics import (
    CrossValidationError,
    IntrinsicsError,
    cross_validate,
    fold_partitions,
    select_by_cross_validation,
)
from calibration.observations import Detection
from calibration.synthetic import plan_views, synthetic_detections
from calibration.targets import Chessboard

BOARD = Chessboard(9, 6, 30.0)
K = np.array([[1100.0, 0, 640], [0, 1100.0, 480], [0, 0, 1]])
TRUTH = CameraModel("division", 1280, 960, K, np.array([-0.12]))


def _data(seed: int, n_views: int = 14) -> list[Detection]:
    rng = np.random.default_rng(seed)
    return synthetic_detections(TRUTH, BOARD, plan_views(TRUTH, BOARD, n_views, rng), 0.3, rng)


def test_partitions_are_the_mod_k_split_then_seeded_random_ones() -> None:
    parts = fold_partitions(13, 3, 5)
    assert len(parts) == 5
    assert [list(f) for f in parts[0]] == [list(range(f, 13, 3)) for f in range(3)]
    for folds in parts:
        assert sorted(np.concatenate(folds).tolist()) == list(range(13))       # disjoint, every view once
        assert sorted(len(f) for f in folds) == [4, 4, 5]
    assert any(not np.array_equal(parts[1][0], parts[r][0]) for r in range(2, 5))
    again = fold_partitions(13, 3, 5)
    assert all(np.array_equal(a, b) for p, q in zip(parts, again, strict=True) for a, b in zip(p, q, strict=True))


def test_the_statistic_is_the_median_over_partitions_and_the_first_is_the_old_split() -> None:
    dets = _data(5)
    one = cross_validate(dets, BOARD, "division", 2, repeats=1)
    four = cross_validate(dets, BOARD, "division", 2, repeats=4)
    assert four["repeats"] == 4 and len(four["per_partition_rms_px"]) == 4 and not four["failed"]
    assert four["per_partition_rms_px"][0] == pytest.approx(one["projection_difference_rms_px"], rel=1e-5)
    assert four["pairs"] == one["pairs"] and len(four["folds"]) == 2
    assert four["projection_difference_rms_px"] == pytest.approx(float(np.median(four["per_partition_rms_px"])),
                                                                 rel=1e-5)
    lo, hi = four["spread_px"]
    assert min(four["per_partition_rms_px"]) <= lo <= hi <= max(four["per_partition_rms_px"])
    # the right model: its halves agree within what their uncertainties explain
    assert four["projection_difference_rms_px"] < 4 * four["expected_from_uncertainty_px"]
    with pytest.raises(IntrinsicsError, match="repeats >= 1"):
        cross_validate(dets, BOARD, "division", 2, repeats=0)


def _failing_when_together(monkeypatch: pytest.MonkeyPatch, names: set[str]) -> None:
    """Folds holding all of ``names`` cannot be calibrated (as a model the fold's views cannot carry)."""
    real = crossval.calibrate

    def calibrate(dets: Any, *a: Any, **kw: Any) -> Any:
        if names <= {d.image for d in dets} and len(dets) < 10:
            raise IntrinsicsError("this fold's views cannot carry the model")
        return real(dets, *a, **kw)

    monkeypatch.setattr(crossval, "calibrate", calibrate)


def test_failed_partitions_count_as_infinite_and_half_or_more_refuse(monkeypatch: pytest.MonkeyPatch) -> None:
    dets = _data(6)
    names = [d.image for d in dets]
    _failing_when_together(monkeypatch, {names[0], names[1]})
    parts = fold_partitions(len(dets), 2, 6)
    together = [any({0, 1} <= set(f.tolist()) for f in folds) for folds in parts]
    assert not together[0]                                            # i mod 2 puts them apart
    if 2 * sum(together) >= len(parts):
        with pytest.raises(CrossValidationError, match="cannot carry the division model"):
            cross_validate(dets, BOARD, "division", 2, repeats=6)
    else:
        cv = cross_validate(dets, BOARD, "division", 2, repeats=6)
        assert len(cv["failed"]) == sum(together)
        assert [v is None for v in cv["per_partition_rms_px"]] == together
        ok = [v for v in cv["per_partition_rms_px"] if v is not None]
        assert cv["projection_difference_rms_px"] >= float(np.median(ok))   # the failures count as infinite
    # a pair every partition splits apart never fails; one in a fold always does: refused with the reason
    monkeypatch.undo()
    _failing_when_together(monkeypatch, {names[2]})
    with pytest.raises(CrossValidationError, match="6 of 6 partitions"):
        cross_validate(dets, BOARD, "division", 2, repeats=6)


def test_selection_reports_the_partitions_and_refuses_a_candidate_with_the_reason(
        monkeypatch: pytest.MonkeyPatch) -> None:
    dets = _data(7)
    real = crossval.calibrate

    def calibrate(d: Any, target: Any, model: str, **kw: Any) -> Any:
        if model == "opencv8" and len(d) < 10:
            raise IntrinsicsError("too few views for opencv8 here")
        return real(d, target, model, **kw)

    monkeypatch.setattr(crossval, "calibrate", calibrate)
    res, sel = select_by_cross_validation(dets, BOARD, [("division", False), ("opencv8", False)], repeats=3)
    assert sel["repeats"] == 3 and "over 3 partitions" in sel["rule"]
    assert sel["chosen"] == {"model": "division", "board_warp": False}
    div, o8 = sel["candidates"]
    assert div["chosen"] and len(div["cross_validation_spread_px"]) == 2
    assert "3 of 3 partitions" in o8["refused"] and "cannot carry the opencv8 model" in o8["refused"]
    assert sel["cross_validation"]["repeats"] == 3


# -- the automatic count (repeats="auto"): a sequential rule over the candidates jointly --------------------------

def test_the_medians_interval_is_the_t_scaled_standard_error_of_a_median_of_logs() -> None:
    from scipy.stats import t

    v = [0.2, 0.3, 0.25, 0.4]
    sd = float(np.std(np.log(v), ddof=1))
    assert crossval.median_half_width(v) == pytest.approx(t.ppf(0.95, 3) * np.sqrt(np.pi / 2) * sd / 2.0)
    assert crossval.median_half_width([0.3, 0.3, 0.3]) == 0.0                   # no scatter: settled
    assert crossval.median_half_width([0.3]) == np.inf                           # one value says nothing
    assert crossval.median_half_width([0.3, np.inf, 0.2]) == np.inf              # a failed partition
    # more partitions of the same scatter: a narrower interval
    assert crossval.median_half_width(v * 2) < crossval.median_half_width(v)


@functools.cache
def _strong_division(seed: int) -> list[Detection]:
    """(Made once per seed and shared: no test changes it.)"""
    truth = CameraModel("division", 1280, 960, np.array([[700.0, 0, 640], [0, 700.0, 480], [0, 0, 1]]),
                        np.array([-0.35]))
    rng = np.random.default_rng(seed)
    return synthetic_detections(truth, BOARD, plan_views(truth, BOARD, 14, rng), 0.3, rng)


@pytest.fixture(scope="module")
def each_fit_once() -> Iterator[None]:
    """crossval's ``calibrate``, each distinct fit solved once for the module: the selections below draw
    the same seeded partitions of the same views with the same models (an automatic count, then eight fixed
    partitions; the same candidates in two tests), and a fit is a deterministic function of its views, model
    and options, so a repeated call gets the result the first one computed (read only by crossval). A call
    that raises is not kept. Keyed by the views' identities, which the key's kept list holds alive."""
    fits: dict[tuple[Any, ...], tuple[list[Detection], Any]] = {}
    real = crossval.calibrate

    def calibrate(dets: Sequence[Detection], target: Any, model: str, **kw: Any) -> Any:
        key = (tuple(map(id, dets)), id(target), model, tuple(sorted(kw.items())))
        if key not in fits:
            fits[key] = (list(dets), real(dets, target, model, **kw))
        return fits[key][1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(crossval, "calibrate", calibrate)
        yield


def test_auto_stops_early_when_the_choice_is_plain_and_chooses_as_eight_fixed_partitions(each_fit_once: None) -> None:
    # a strong wide-angle lens: opencv5 cannot describe it, its halves differ by px; division's by tenths
    dets = _strong_division(1)
    cands = [("opencv5", False), ("division", False)]
    res, sel = select_by_cross_validation(dets, BOARD, cands)
    assert crossval.CV_MIN_REPEATS <= sel["repeats"] < crossval.CV_REPEATS
    assert sel["repeats_rule"].startswith("auto") and f"over {sel['repeats']} partitions" in sel["rule"]
    assert sel["chosen"] == {"model": "division", "board_warp": False}
    o5, div = sel["candidates"]
    lo5, _ = o5["cross_validation_interval_px"]
    _, hi = div["cross_validation_interval_px"]
    assert hi < (1 - crossval.SELECT_MARGIN) * lo5            # settled beyond both intervals (the stated rule)
    assert div["partitions"] == sel["repeats"] == len(sel["cross_validation"]["per_partition_rms_px"])
    _, fixed = select_by_cross_validation(dets, BOARD, cands, repeats=8)
    assert fixed["repeats"] == 8 and fixed["repeats_rule"] == "fixed" and fixed["chosen"] == sel["chosen"]


def test_auto_draws_all_eight_when_the_candidates_are_close(each_fit_once: None) -> None:
    # a flat board: the warp's two heights are ~0, the two candidates' medians are within each other's scatter
    dets = _strong_division(1)
    res, sel = select_by_cross_validation(dets, BOARD, [("division", False), ("division", True)])
    assert sel["repeats"] == crossval.CV_REPEATS
    assert all(c["partitions"] == crossval.CV_REPEATS for c in sel["candidates"])
    assert sel["chosen"] == {"model": "division", "board_warp": False}


def test_auto_for_one_model_stops_once_its_median_is_known_to_the_margin() -> None:
    dets = _data(5)
    cv = cross_validate(dets, BOARD, "division", 2)
    per = cv["per_partition_rms_px"]
    assert crossval.CV_MIN_REPEATS <= cv["repeats"] == len(per) <= crossval.CV_REPEATS
    settled = [crossval.median_half_width(per[:n]) <= np.log1p(crossval.SELECT_MARGIN)
               for n in range(crossval.CV_MIN_REPEATS, len(per) + 1)]
    assert not any(settled[:-1])                               # it did not go on past the rule's stop ...
    assert settled[-1] or len(per) == crossval.CV_REPEATS      # ... nor stop before it
    with pytest.raises(IntrinsicsError, match="or 'auto'"):
        cross_validate(dets, BOARD, "division", 2, repeats="some")  # type: ignore[arg-type]


def test_a_candidate_out_of_the_race_stops_drawing_and_the_choice_is_the_fixed_ones(each_fit_once: None) -> None:
    # opencv5 after division on a lens it cannot describe: beaten by the simpler one beyond both intervals
    dets = _strong_division(1)
    cands = [("division", False), ("division", True), ("opencv5", False)]
    _, sel = select_by_cross_validation(dets, BOARD, cands)
    div, warp, o5 = sel["candidates"]
    assert o5["partitions"] < div["partitions"] == warp["partitions"] == sel["repeats"] == crossval.CV_REPEATS
    assert div["cross_validation_interval_px"][1] < (1 - crossval.SELECT_MARGIN) * o5["cross_validation_interval_px"][0]
    _, fixed = select_by_cross_validation(dets, BOARD, cands, repeats=8)
    assert fixed["chosen"] == sel["chosen"] == {"model": "division", "board_warp": False}
