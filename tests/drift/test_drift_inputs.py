"""The drift section of cell.yaml, the sim camera's fault (at once and as a ramp), and the REST routes'
answers to what a client gets wrong (no drift configured, a bad fault, a role too low)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cellctl.config import ConfigError, parse_config
from drivers.sim.camera_fault import CameraFault, Fault
from tests.support.app import in_process_cell

MARKS = [[250.0, 140.0, 0.0], [650.0, 140.0, 0.0], [250.0, -140.0, 0.0]]


def test_the_drift_section_is_checked() -> None:
    cfg = parse_config({"drift": {"fiducials": {"marks_mm": MARKS}}})
    assert cfg.drift is not None and cfg.drift.every_cycles == 10 and cfg.drift.baseline_checks == 20
    with pytest.raises(ConfigError, match="needs 3 or more"):
        parse_config({"drift": {"fiducials": {"marks_mm": MARKS[:2]}}})
    with pytest.raises(ConfigError, match="either marks_mm"):
        parse_config({"drift": {"fiducials": {}}})
    with pytest.raises(ConfigError, match="not a target of this cell"):
        parse_config({"drift": {"fiducials": {"target": "nope", "T_base_target_ur": [0, 0, 0, 0, 0, 0]}}})
    with pytest.raises(ConfigError, match="baseline_checks"):
        parse_config({"drift": {"fiducials": {"marks_mm": MARKS}, "baseline_checks": 1}})


def test_a_fault_applies_at_once_or_as_a_ramp() -> None:
    f = CameraFault()
    T = np.eye(4)
    assert f.apply(T) is T  # no fault: the nominal pose
    f.set(Fault((1.0, 0.0, 0.0), (0.0, 0.0, 0.0)), now_s=0.0)
    assert f.apply(T, now_s=0.0)[0, 3] == pytest.approx(0.001)
    f.set(Fault((3.0, 0.0, 0.0), (0.0, 0.0, 2.0)), ramp_s=10.0, now_s=100.0)
    assert f.now(100.0).shift_mm[0] == pytest.approx(1.0)  # from the fault in force
    assert f.now(105.0).shift_mm[0] == pytest.approx(2.0) and f.now(105.0).rot_deg[2] == pytest.approx(1.0)
    assert f.now(200.0).shift_mm[0] == pytest.approx(3.0)
    R = f.apply(T, now_s=200.0)[:3, :3]
    assert np.degrees(np.arctan2(R[1, 0], R[0, 0])) == pytest.approx(2.0)


def test_rest_answers_what_the_client_got_wrong(tmp_path: Path) -> None:
    with in_process_cell(tmp_path) as app:  # the built-in virtual cell: a sim camera, no drift section
        http = app.http()
        r = http.get("/drift")
        assert r.status_code == 404 and r.json()["error"]["code"] == "no_drift"
        assert http.post("/drift/check").status_code == 404
        r = http.post("/sim/faults", json={"camera_shift_mm": [0.0, 0.0, 500.0]})
        assert r.status_code == 422, r.text
        r = http.post("/sim/faults", json={"camera_rot_deg": [True, 0, 0]})
        assert r.status_code == 422, r.text
        r = http.post("/sim/faults", json={"camera_shift_mm": [0.2, 0.0, 0.0], "ramp_s": 60})
        assert r.status_code == 200 and r.json()["target_shift_mm"] == [0.2, 0.0, 0.0], r.text
        assert http.get("/sim/truth").json()["camera_fault"]["ramp_s"] == 60
        http.post("/sim/faults", json={})  # back to nominal (the roles: tests/cellctl/test_auth.py)
