"""The root of every cellctl error: ``CellctlError``.

Every exception class defined in ``cellctl`` derives from it (``tests/test_error_roots.py`` holds
that), besides the builtin it also is (``ValueError`` for bad input, ``LookupError`` for something
not found, ``RuntimeError`` for a state that refuses the request), so callers that catch the
builtin keep working. The REST API (``cellctl.api.errors``) maps the roots: ``CellctlError``,
``calibration.CalibrationError``, ``vision.errors.VisionError`` and ``drivers.errors.DriverError``.
"""

from __future__ import annotations


class CellctlError(Exception):
    """Root of every cellctl error. Messages say what was wrong and what to do about it."""
