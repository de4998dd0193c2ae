"""``handeye-capture`` with ``dof: 4`` on the virtual cell: stations that only turn about base z and
shift, a 4-DOF hand-eye near the truth (the plate height given), stored inactive; and ``dof: 4``
without ``target_z_mm`` refused at once."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration import geometry as g
from cellctl.routines.handeye_dof4_capture import dof4_stations
from tests.support.app import in_process_cell


def test_the_stations_only_turn_about_z_and_shift() -> None:
    T0 = g.ur_pose_to_transform([0.4, 0.0, 0.55, math.pi, 0.0, 0.0])
    C0 = g.make_transform(np.eye(3), [0.0, 0.0, 0.5])
    stations = dof4_stations("eye-in-hand", T0, C0, np.array([0.06, 0.06, 0.0]), 40.0, 0.15)
    turns = []
    for _, T in stations:
        R = T0[:3, :3].T @ T[:3, :3]  # relative to the start, in the tool frame
        assert abs(R[2, 2] - 1.0) < 1e-9  # the tool's z axis is unchanged: no tilt
        turns.append(math.degrees(math.atan2(T[1, 0], T[0, 0]) - math.atan2(T0[1, 0], T0[0, 0])))
    turns = [((t + 180) % 360) - 180 for t in turns]
    assert max(turns) >= 39 and min(turns) <= -39
    assert len({round(float(T[2, 3]), 4) for _, T in stations}) >= 3  # heights vary too


def _wait(http: Any, job_id: str, timeout_s: float = 400) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while (job := http.get(f"/jobs/{job_id}").json())["state"] == "running":
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    return dict(job)


def test_dof4_capture_on_the_virtual_cell(tmp_path: Path) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        truth = http.get("/sim/truth").json()
        r = http.post("/routines/handeye-capture", json={"dof": 4})
        assert r.status_code == 422 and "target_z_mm" in r.json()["error"]["message"]
        added = http.post("/calibrations", json=truth["camera"], params={"note": "the true lens"})
        assert http.post(f"/calibrations/{added.json()['id']}/activate").status_code == 200
        z_mm = truth["targets"]["plate"]["T_base_target"][2][3] * 1e3
        r = http.post("/routines/handeye-capture", json={"dof": 4, "target_z_mm": z_mm, "stations": 6,
                                                         "max_stations": 14, "speed_m_s": 0.25})
        assert r.status_code == 202, r.text
        job = _wait(http, r.json()["id"])
        assert job["state"] == "succeeded", job
        res = job["result"]
        assert res["dof"] == 4 and res["activated"] is False and res["stations_used"] >= 6
        stored = http.get(f"/calibrations/{res['calibration_id']}").json()
        assert stored["result"]["dof"] == 4 and stored["active"] is False
        moves = http.get("/audit", params={"action": "robot.move"}).json()
    X, X_true = np.array(res["T_tool_cam"]), np.array(truth["T_tool_cam"])
    err_mm = 1e3 * float(np.linalg.norm(X[:3, 3] - X_true[:3, 3]))
    err_deg = math.degrees(float(np.linalg.norm(g.matrix_to_rotvec(X[:3, :3].T @ X_true[:3, :3]))))
    assert err_mm < max(2.0, 4 * res["uncertainty"]["trans_mm"]), (err_mm, res["uncertainty"])
    assert err_deg < max(0.3, 4 * res["uncertainty"]["rot_deg"]), (err_deg, res["uncertainty"])
    for m in [m for m in moves if "dof 4" in str(m["detail"].get("why", ""))]:
        T = g.ur_pose_to_transform(m["detail"]["pose_ur"])
        assert math.degrees(math.acos(min(1.0, -T[2, 2]))) < 0.01  # every station keeps the tool pointing down
