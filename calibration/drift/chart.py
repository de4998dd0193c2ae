"""An individuals / moving-range (I-MR) control chart and the Western Electric rules.

A drift check gives one number per check (``drift_mm``). The first ``n`` checks after a
calibration changes are the *baseline*: the chart's centre is their mean, and sigma is estimated
from the average moving range (``MR-bar / d2``, ``d2 = 1.128`` for ranges of two consecutive
points), not from the standard deviation: a slow trend inside the baseline widens the limits less.
The individuals limits are ``centre +- 3 sigma``; the moving-range chart's upper limit is
``D4 * MR-bar`` (``D4 = 3.267``).

``min_sigma`` is a floor under sigma (the same unit as the values): a still cell measured by a
precise sensor gives a sigma so small that a change far below what matters would alarm. With the
floor in force the chart is an acceptance chart: the zones are drawn with the floored sigma, and
the run rule counts a point on a side only when it lies at least ``sigma_used - sigma_measured``
from the centre (0 when the floor is not in force: the textbook rule).

Rules, each alarm naming the one that fired (checked in this order):

- ``beyond_3sigma``: one point beyond a 3-sigma limit (Western Electric rule 1);
- ``2_of_3_beyond_2sigma``: two of three consecutive points beyond 2 sigma on the same side (rule 2);
- ``8_in_a_row``: eight consecutive points on the same side of the centre (rule 4).

The moving-range chart's limit is reported (a jump between two checks beyond it is worth a look)
but raises no alarm of its own: a jump that matters moves the point beyond 3 sigma.

Pure: numbers in, numbers out (no I/O, no cellctl).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from calibration import CalibrationError

D2 = 1.128
"""Expected range of two normal samples, in sigma (the moving range's d2)."""
D4 = 3.267
"""The moving-range chart's upper-limit factor for ranges of two."""
RUN_LENGTH = 8

Rule = Literal["beyond_3sigma", "2_of_3_beyond_2sigma", "8_in_a_row"]
RULES: tuple[Rule, ...] = ("beyond_3sigma", "2_of_3_beyond_2sigma", "8_in_a_row")


class ChartError(CalibrationError):
    """A chart cannot be built from these values (too few, not finite)."""


@dataclass(frozen=True)
class Limits:
    """An I-MR chart's limits (the unit of the values)."""

    center: float
    sigma: float
    """The sigma the zones are drawn with (``max(sigma_measured, min_sigma)``)."""
    sigma_measured: float
    """``MR-bar / d2`` from the baseline."""
    mr_bar: float
    n: int
    """How many baseline points set them."""

    @property
    def ucl(self) -> float:
        return self.center + 3.0 * self.sigma

    @property
    def lcl(self) -> float:
        return self.center - 3.0 * self.sigma

    @property
    def mr_ucl(self) -> float:
        """The moving-range chart's upper limit: ``D4 * MR-bar`` (with the floor: at least ``D4 * d2 * sigma``)."""
        return D4 * max(self.mr_bar, D2 * self.sigma)

    @property
    def run_band(self) -> float:
        """How far from the centre a point must lie to count for the run rule (0 without the floor)."""
        return max(0.0, self.sigma - self.sigma_measured)


def limits(values: Sequence[float], min_sigma: float = 0.0) -> Limits:
    """The chart's limits from baseline ``values`` (at least 2, finite)."""
    xs = [float(v) for v in values]
    if len(xs) < 2:
        raise ChartError(f"a chart needs at least 2 baseline points, got {len(xs)}")
    if not all(math.isfinite(v) for v in xs):
        raise ChartError("the baseline holds a value that is not a finite number")
    if not (math.isfinite(min_sigma) and min_sigma >= 0):
        raise ChartError(f"min_sigma must be a finite number >= 0, got {min_sigma}")
    center = sum(xs) / len(xs)
    mrs = [abs(b - a) for a, b in zip(xs, xs[1:], strict=False)]
    mr_bar = sum(mrs) / len(mrs)
    measured = mr_bar / D2
    return Limits(center, max(measured, min_sigma), measured, mr_bar, len(xs))


def rule_fired(lim: Limits, history: Sequence[float]) -> Rule | None:
    """The first rule the last point of ``history`` (the checks since the baseline, oldest first) breaks."""
    if not history:
        return None
    x = float(history[-1])
    c, s = lim.center, lim.sigma
    if not math.isfinite(x) or abs(x - c) > 3.0 * s:
        return "beyond_3sigma"
    last3 = history[-3:]
    if len(last3) == 3 and _side(x, c) != 0 and abs(x - c) > 2.0 * s:
        same = [v for v in last3 if _side(v, c) == _side(x, c) and abs(v - c) > 2.0 * s]
        if len(same) >= 2:
            return "2_of_3_beyond_2sigma"
    run = history[-RUN_LENGTH:]
    if len(run) == RUN_LENGTH:
        band = lim.run_band
        sides = {_side(v, c) if abs(v - c) > band else 0 for v in run}
        if len(sides) == 1 and 0 not in sides:
            return "8_in_a_row"
    return None


def _side(v: float, c: float) -> int:
    return 1 if v > c else (-1 if v < c else 0)


@dataclass
class Chart:
    """A chart that grows its baseline, then judges each new point.

    ``add`` returns ``(state, rule)``: ``("baseline", None)`` while the first ``baseline_n`` points
    set the limits, then ``("ok", None)`` or ``("alarm", rule)``.
    """

    baseline_n: int = 20
    min_sigma: float = 0.0
    baseline: list[float] | None = None
    history: list[float] | None = None
    lim: Limits | None = None

    def __post_init__(self) -> None:
        if self.baseline_n < 2:
            raise ChartError(f"baseline_n must be at least 2, got {self.baseline_n}")
        self.baseline = list(self.baseline or [])
        self.history = list(self.history or [])

    def add(self, value: float) -> tuple[Literal["baseline", "ok", "alarm"], Rule | None]:
        assert self.baseline is not None and self.history is not None
        if self.lim is None:
            self.baseline.append(float(value))
            if len(self.baseline) >= self.baseline_n:
                self.lim = limits(self.baseline, self.min_sigma)
            return "baseline", None
        self.history.append(float(value))
        del self.history[:-RUN_LENGTH]
        rule = rule_fired(self.lim, self.history)
        return ("alarm", rule) if rule is not None else ("ok", None)
