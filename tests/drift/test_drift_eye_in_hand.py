"""A camera on the arm checked from a station (the built-in virtual cell: eye-in-hand, the plate fixed on
the table as the fiducial target): checks from where the robot stands, a bump of the camera on its
bracket alarms, and the re-solve stores a new ``T_tool_cam`` that brings the checks back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from calibration import geometry as g
from cellctl.config import default_config_text, parse_config
from cellctl.store import open_store
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld
from tests.support.app import in_process_cell
from tests.support.truth import activate_truth

BASELINE = 3


def eye_in_hand_cell(tmp: Path) -> Path:
    cfg = yaml.safe_load(default_config_text())
    scene = tmp / "scene.yaml"
    scene.write_text(BUILTIN_SCENES["fixed-camera"].with_name("virtual-cell.yaml").read_text())  # a world of its own
    for dev in (cfg["cameras"]["cam0"], cfg["robots"]["robot0"]):
        dev["settings"]["scene"] = str(scene)
    truth = SimWorld(load_scene(scene)).truth()
    T_base_plate = truth["targets"]["plate"]["T_base_target"]
    cfg["store"] = {"path": str(tmp / "cell.db")}
    cfg["drift"] = {"fiducials": {"target": "plate", "T_base_target_ur": [float(v) for v in
                                                                           g.transform_to_ur_pose(T_base_plate)]},
                    "every_s": 0, "baseline_checks": BASELINE}
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with open_store(parse_config(cfg)) as store:
        activate_truth(store, truth, "eye-in-hand", T_base_plate, robot_noise=False)
    return path


def test_a_camera_on_the_arm_is_checked_and_resolved_from_a_station(tmp_path: Path) -> None:
    with in_process_cell(tmp_path, eye_in_hand_cell(tmp_path)) as app:
        http = app.http()
        states = [http.post("/drift/check").json() for _ in range(BASELINE + 1)]
        assert [s["state"] for s in states] == ["baseline"] * BASELINE + ["ok"], states
        assert all(s["drift_mm"] < 0.1 and s["seen"] == 49 for s in states), states
        assert http.post("/sim/faults", json={"camera_shift_mm": [0.0, 0.4, 0.0]}).status_code == 200
        rec = http.post("/drift/check").json()
        assert rec["state"] == "alarm" and rec["drift_mm"] > 0.3, rec
        out = http.post("/drift/resolve").json()
        assert "T_tool_cam" in out and out["verdict"]["ok"] and abs(out["shift_mm"] - 0.4) < 0.08, out
        truth = http.get("/sim/truth").json()
        bumped = np.linalg.inv(np.array(truth["T_base_tool"])) @ np.array(truth["T_base_cam"])
        _, trans = g.transform_error(np.array(out["T_tool_cam"]), bumped)
        assert trans * 1e3 < 0.1, trans  # the robot's repeatability (0.02 mm) and the fit
        assert http.post(f"/calibrations/{out['calibration_id']}/activate").status_code == 200
        after = [http.post("/drift/check").json() for _ in range(BASELINE + 1)]
        assert after[-1]["state"] == "ok" and all(a["drift_mm"] < 0.1 for a in after), after
