"""vision.image.wrap_deg, the one angle wrap: degrees into (-180, 180]."""

from __future__ import annotations

import math

import pytest

from vision.image import wrap_deg


@pytest.mark.parametrize(("a", "want"), [(0.0, 0.0), (180.0, 180.0), (-180.0, 180.0), (190.0, -170.0),
                                         (-190.0, 170.0), (540.0, 180.0), (-540.0, 180.0), (359.5, -0.5),
                                         (720.25, 0.25), (-0.0, 0.0)])
def test_wraps_into_the_half_open_interval(a: float, want: float) -> None:
    assert wrap_deg(a) == pytest.approx(want, abs=1e-12)


def test_every_angle_lands_in_range_and_keeps_its_direction() -> None:
    for k in range(-2000, 2001):
        a = k * 0.37
        w = wrap_deg(a)
        assert -180.0 < w <= 180.0
        assert math.isclose(math.cos(math.radians(w)), math.cos(math.radians(a)), abs_tol=1e-9)
        assert math.isclose(math.sin(math.radians(w)), math.sin(math.radians(a)), abs_tol=1e-9)
