"""N-point (jog-to-mark) calibration: the image→robot map fitted to marks the tool was jogged to,
and its verdict.

Modules: ``fit`` (``fit_npoint``: affine, similarity or homography, chosen by leave-one-out; the
predicted error over the field), ``verdict`` (``assess_npoint``: can these marks support this
map?). Virtual jog-to-mark data with truth is ``calibration.synthetic.simulate_npoint``; the tool
centre that jog-to-mark can add is ``calibration.handeye.fit_tool_centre``.
Everything public is exported here: ``from calibration.npoint import X`` is the interface.
"""

from calibration.npoint.fit import (
    MIN_POINTS,
    MODELS,
    NPointError,
    NPointResult,
    affine_par,
    apply_h,
    check_layout,
    fit_model,
    fit_npoint,
    loo_errors_mm,
)
from calibration.npoint.verdict import MAX_LOO_RMS_MM, assess_npoint

__all__ = [
    "MAX_LOO_RMS_MM", "MIN_POINTS", "MODELS", "NPointError", "NPointResult", "affine_par", "apply_h",
    "assess_npoint", "check_layout", "fit_model", "fit_npoint", "loo_errors_mm",
]
