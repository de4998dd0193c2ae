"""After a restart the drift monitor rebuilds the active calibration's chart from the stored checks: the
limits are the baseline's, the state is the last check's (an alarm shows at once on /metrics), and a
newly activated calibration starts a new baseline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.drift import limits
from cellctl.cell import Cell
from cellctl.config import parse_config
from cellctl.jobs import JobManager
from cellctl.services import Services
from cellctl.store import open_store
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld


def test_the_chart_and_the_alarm_come_back_from_the_store(tmp_path: Path) -> None:
    truth = SimWorld(load_scene(BUILTIN_SCENES["fixed-camera"])).truth()
    config = parse_config({
        "cell_id": "restart", "store": {"path": str(tmp_path / "cell.db")},
        "cameras": {"cam0": {"kind": "sim", "settings": {"scene": "fixed-camera"}}},
        "calibration": {"camera": "cam0", "robot": "robot0", "setup": "eye-to-hand"},
        "drift": {"fiducials": {"marks_mm": [[300, 0, 0], [600, 0, 0], [450, 100, 0]]}, "baseline_checks": 5}})
    baseline = [0.010, 0.012, 0.011, 0.013, 0.010]
    with open_store(config) as store:
        cam = store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="t")
        he = {"setup": "eye-to-hand", "T_base_cam": truth["T_base_cam"], "T_tool_target": np.eye(4).tolist(),
              "uncertainty": {"covariance": (np.eye(6) * 1e-10).tolist()}}
        first = store.save_calibration("handeye", "cam0", "robot0", he, {}, creator="t")
        store.activate(cam.id, "t")
        store.activate(first.id, "t")
        for k, v in enumerate([*baseline, 0.011, 0.4]):
            state = "baseline" if k < 5 else ("ok" if v < 0.1 else "alarm")
            store.add_drift_check("cam0", first.id, {"t": float(k), "drift_px": v * 2.8, "drift_mm": v,
                                                     "drift_deg": 0.0, "state": state, "rule": None})
        services = Services(config, Cell(config), store, JobManager())  # the service after a restart
        monitor = services.drift
        assert monitor is not None and not monitor.alarm  # nothing read yet
        body = monitor.public()
        assert body["state"] == "alarm" and monitor.alarm and len(body["records"]) == 7
        lim = limits(baseline, config.drift.min_sigma_mm if config.drift else 0.0)
        assert body["limits"]["ucl_mm"] == pytest.approx(lim.ucl, abs=1e-6)
        assert body["limits"]["center_mm"] == pytest.approx(lim.center, abs=1e-6)
        assert 'cellctl_drift_alarm{camera="cam0"} 1.0' in services.metrics.render().decode()
        second = store.save_calibration("handeye", "cam0", "robot0", he, {}, creator="t")
        store.activate(second.id, "t")
        body = monitor.public()
        assert body["state"] == "baseline" and body["limits"]["ucl_mm"] is None and not monitor.alarm
        assert body["calibration_id"] == second.id
        assert 'cellctl_drift_alarm{camera="cam0"} 0.0' in services.metrics.render().decode()
