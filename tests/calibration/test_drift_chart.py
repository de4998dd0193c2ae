"""The I-MR chart and the Western Electric rules against hand-computed charts, a ramp and a bump."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.drift import Chart, ChartError, limits, rule_fired


def test_limits_by_hand() -> None:
    # values 1, 3, 2, 4, 5: mean 3; moving ranges 2, 1, 2, 1 -> MR-bar 1.5; sigma 1.5 / 1.128
    lim = limits([1, 3, 2, 4, 5])
    assert lim.center == pytest.approx(3.0)
    assert lim.mr_bar == pytest.approx(1.5)
    assert lim.sigma == pytest.approx(1.5 / 1.128)
    assert lim.ucl == pytest.approx(3.0 + 3 * 1.5 / 1.128)
    assert lim.lcl == pytest.approx(3.0 - 3 * 1.5 / 1.128)
    assert lim.mr_ucl == pytest.approx(3.267 * 1.5)
    assert lim.run_band == 0.0


def test_the_sigma_floor_widens_the_zones_and_bands_the_run_rule() -> None:
    lim = limits([0.10, 0.11, 0.10, 0.11], min_sigma=0.02)  # MR-bar 0.01 -> sigma 0.00887 < floor
    assert lim.sigma == pytest.approx(0.02)
    assert lim.sigma_measured == pytest.approx(0.01 / 1.128)
    assert lim.run_band == pytest.approx(0.02 - 0.01 / 1.128)
    assert lim.ucl == pytest.approx(0.105 + 0.06)


def test_each_rule_by_hand() -> None:
    lim = limits([0.0, 1.128] * 5)  # centre 0.564, MR-bar 1.128 -> sigma 1
    c = lim.center
    assert lim.sigma == pytest.approx(1.0)
    assert rule_fired(lim, [c + 3.1]) == "beyond_3sigma"
    assert rule_fired(lim, [c - 3.1]) == "beyond_3sigma"
    assert rule_fired(lim, [c + 2.9]) is None
    assert rule_fired(lim, [c + 2.5, c, c + 2.5]) == "2_of_3_beyond_2sigma"
    assert rule_fired(lim, [c + 2.5, c - 2.5, c + 0.1]) is None
    assert rule_fired(lim, [c + 2.5, c - 1.0, c - 2.1]) is None  # one of three beyond 2 sigma low
    assert rule_fired(lim, [c - 2.5, c + 2.5, c - 2.1]) == "2_of_3_beyond_2sigma"
    assert rule_fired(lim, [c + 0.5] * 7) is None
    assert rule_fired(lim, [c + 0.5] * 8) == "8_in_a_row"
    assert rule_fired(lim, [c + 0.5] * 7 + [c - 0.5]) is None
    assert rule_fired(lim, [c + 0.5] * 8 + [c]) is None  # a point on the centre breaks the run


def test_the_run_rule_with_the_floor_needs_points_beyond_the_band() -> None:
    lim = limits([0.0, 0.01] * 10, min_sigma=0.1)  # measured sigma ~0.0089, used 0.1
    c = lim.center
    assert rule_fired(lim, [c + 0.05] * 8) is None  # inside the band: noise the floor says is irrelevant
    assert rule_fired(lim, [c + 0.095] * 8) == "8_in_a_row"


def test_a_bump_alarms_at_once_and_a_ramp_within_its_slope() -> None:
    rng = np.random.default_rng(1)
    noise = 0.01
    for kind in ("bump", "ramp"):
        chart = Chart(baseline_n=20)
        for v in rng.normal(0.1, noise, 20):
            assert chart.add(float(v)) == ("baseline", None)
        assert chart.lim is not None
        states = []
        for k in range(40):
            shift = 0.1 if kind == "bump" else 0.004 * k  # bump 10 sigma; ramp 0.4 sigma per check
            states.append(chart.add(float(rng.normal(0.1, noise) + shift)))
        first = next(i for i, (s, _) in enumerate(states) if s == "alarm")
        if kind == "bump":
            assert first == 0 and states[0][1] == "beyond_3sigma"
        else:
            assert 3 <= first <= 12, states  # caught while the ramp is still small (< 5 sigma)


def test_no_false_alarm_in_500_still_checks_with_a_floor() -> None:
    rng = np.random.default_rng(7)
    chart = Chart(baseline_n=20, min_sigma=0.02)
    for v in np.abs(rng.normal(0.0, 0.005, 520)) + 0.05:
        chart.add(float(v))
    # a fresh run of the same noise, judged point by point
    alarms = [chart.add(float(v)) for v in np.abs(rng.normal(0.0, 0.005, 500)) + 0.05]
    assert [a for a in alarms if a[0] == "alarm"] == []


def test_bad_input_is_refused_clearly() -> None:
    with pytest.raises(ChartError, match="at least 2"):
        limits([1.0])
    with pytest.raises(ChartError, match="finite"):
        limits([1.0, float("nan")])
    with pytest.raises(ChartError, match="baseline_n"):
        Chart(baseline_n=1)
