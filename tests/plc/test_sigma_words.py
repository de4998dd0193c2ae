"""A pick's 1-sigma on integer registers (µm, 0.001 deg): a positive sigma below the resolution reads 1,
never 0, so that a PLC cannot mistake a very good pick for an exact one; unknown reads -1."""

from __future__ import annotations

import math

import pytest

from cellctl.plc.modbus_map import PRODUCTION_FIELDS, field_words, sigma_words, words_int32


@pytest.mark.parametrize(("sigma", "expected"), [
    (0.0004, 1), (0.0006, 1), (0.061, 61), (0.0615, 62), (2.5, 2500), (0.0, 0),
    (None, -1), (math.nan, -1), (-0.2, -1),
])
def test_a_sigma_on_registers_is_never_rounded_to_exact(sigma: float | None, expected: int) -> None:
    assert words_int32(sigma_words(sigma, 1000)) == expected


def test_the_production_blocks_last_sigma_reads_its_resolution_not_zero() -> None:
    last_deg = next(f for f in PRODUCTION_FIELDS if f.name == "LAST_SIGMA_MDEG")
    assert words_int32(field_words(last_deg, 0.0003, 1000.0)) == 1
    assert words_int32(field_words(last_deg, -1, 1000.0)) == -1
    cycle = next(f for f in PRODUCTION_FIELDS if f.name == "CYCLE_MEDIAN_MS")
    assert words_int32(field_words(cycle, 0.3, 1.0)) == 0  # not a sigma: rounded as it is
