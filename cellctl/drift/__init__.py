"""Drift monitoring of a calibrated cell (docs/drift.md): fiducial checks on frames the cell takes
anyway, an I-MR chart per active calibration, alarms to every front end, a gated re-solve."""
