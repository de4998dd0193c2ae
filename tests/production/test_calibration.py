"""The production cell calibrates its hand-eye by its own routine: handeye-capture, the robot carrying
the plate in front of the fixed camera (eye-to-hand), from the camera's active intrinsics.

(intrinsics-capture plans its views for a camera on the arm and does not reach an ok verdict on
this cell: docs/production.md; the camera's true calibration stands in for it here.)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calibration import geometry as g
from tests.support.production_cell import production_config
from tests.support.served import run_job, start_served, stop_served


def test_handeye_capture_calibrates_the_production_cell(tmp_path: Path) -> None:
    served = start_served(tmp_path, production_config(tmp_path, time_scale=0.0))
    try:
        http = served.client(timeout_s=60)
        job = run_job(http, "handeye-capture", {}, timeout_s=600)
        assert job["state"] == "succeeded", job
        res = job["result"]
        assert res["verdict"]["ok"] is True and res["setup"] == "eye-to-hand", res["verdict"]
        truth = http.get("/sim/truth").json()
        rot, trans = g.transform_error(np.array(res["T_base_cam"]), np.array(truth["T_base_cam"]))
        sig = res["uncertainty"]
        assert trans * 1e3 < max(4 * sig["trans_mm"], 0.2), (trans * 1e3, sig)
        assert math.degrees(rot) < max(4 * sig["rot_deg"], 0.05), (math.degrees(rot), sig)
    finally:
        stop_served(served)
