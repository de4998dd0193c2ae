"""Camera and hand-eye calibration: pure geometry on arrays and files (no driver, no service).

At the top, what every job shares: ``geometry``, ``camera_model``, ``targets``, ``observations``
(the ``Detection``), ``verdict``. Each job is a package with its public names in its ``__init__``:
``detect``, ``intrinsics``, ``pose``, ``handeye``, ``npoint``, ``measure``, ``report``, ``io`` and
``synthetic`` (data with truth). The map: docs/packages.md.
"""

from __future__ import annotations

__all__ = ["CalibrationError"]


class CalibrationError(ValueError):
    """Root of every error ``calibration`` raises on purpose: bad input or data that cannot give an answer.

    A ``ValueError`` so callers that treat bad input as one keep working; callers that must tell
    bad input from a bug catch ``CalibrationError`` (a bare ``ValueError`` from numpy is a bug).
    """
