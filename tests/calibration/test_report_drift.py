"""A re-solved hand-eye's report shows the shift it corrects and the drift history behind it."""

from __future__ import annotations

import numpy as np

from calibration.report import calibration_report
from calibration.report.drift import drift_html


def test_the_drift_section_shows_the_shift_and_the_history() -> None:
    result = {"setup": "eye-to-hand", "T_base_cam": np.eye(4).tolist(),
              "drift_resolve": {"from_calibration_id": 3, "shift_mm": 0.301, "shift_deg": 0.0501, "rms_px": 0.012,
                                "fiducials_seen": 6, "sigma_trans_mm": 0.004, "sigma_rot_deg": 0.0003,
                                "history": [{"t": 1.7e9, "drift_mm": 0.004, "drift_deg": 0.001, "state": "ok",
                                             "rule": None},
                                            {"t": None, "drift_mm": 0.41, "drift_deg": 0.05, "state": "alarm",
                                             "rule": "beyond_3sigma"}]}}
    page = calibration_report("handeye", result)
    assert "Drift re-solve" in page and "re-solved from calibration" in page
    assert "0.301 mm" in page and "beyond_3sigma" in page and "the last 2" in page
    assert drift_html({"setup": "eye-to-hand"}) == ""
