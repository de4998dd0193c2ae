"""Drift of a calibrated cell: control charts on drift checks, fiducial measurements, the camera re-solve.

``chart``: the individuals / moving-range chart and the Western Electric rules; ``fiducials``:
measure fixed marks in a frame and compare them with where the calibration puts them, and
re-solve the camera's pose from them (intrinsics kept). Pure: arrays in, numbers out.
"""

from __future__ import annotations

from calibration.drift.chart import RULES, Chart, ChartError, Limits, Rule, limits, rule_fired

__all__ = ["RULES", "Chart", "ChartError", "Limits", "Rule", "limits", "rule_fired"]
