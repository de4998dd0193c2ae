"""Errors that say what is wrong (issue 36): a JSON syntax error names its line and column; a body sent
without ``Content-Type: application/json`` says so; a number out of range on a field in metres hints at
the unit; the motion owner and the audit name the token and the robot."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from tests.support.app import in_process_cell


def test_error_texts_say_what_is_wrong(tmp_path: Path) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        bad = '{"pose_ur": {"x_m": 0.4, "y_m": 0.0,\n  "z_m": , "rx_rad": 3.14, "ry_rad": 0, "rz_rad": 0}}'
        r = http.post("/robots/robot0/move", content=bad, headers={"Content-Type": "application/json"})
        msg = r.json()["error"]["message"]
        assert r.status_code == 422 and "line 2, column 10" in msg and "Expecting value" in msg, msg
        assert "body.5" not in msg  # no character offset shown as a field

        r = http.post("/map", content='{"u_px": 640, "v_px": 480, "plane_z_mm": 0}')  # no Content-Type
        msg = r.json()["error"]["message"]
        assert r.status_code == 422 and "Content-Type: application/json" in msg, msg
        assert "valid dictionary" not in msg

        r = http.post("/robots/robot0/move", json={"pose_ur": {"x_m": 400, "y_m": 0, "z_m": 0.5, "rx_rad": 3.14,
                                                               "ry_rad": 0, "rz_rad": 0}})
        msg = r.json()["error"]["message"]
        assert r.status_code == 422 and "pose_ur.x_m" in msg and "metres" in msg and "0.4 m" in msg, msg


def test_the_motion_owner_and_the_audit_name_the_token_and_the_robot(tmp_path: Path) -> None:
    with in_process_cell(tmp_path) as a, a.http() as http:
        owners: list[object] = []
        pose = {"x_m": 0.4, "y_m": 0.1, "z_m": 0.5, "rx_rad": 3.14159, "ry_rad": 0, "rz_rad": 0}
        mover = threading.Thread(target=lambda: owners.append(
            http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.05}).status_code))
        mover.start()
        seen = None
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and seen is None:
            seen = http.get("/robots/robot0/motion").json().get("owner")
            time.sleep(0.05)
        mover.join(30)
        assert owners == [200]
        assert seen is not None and seen["who"] == "session", seen  # the token's name, not "direct"
        move = next(e for e in http.get("/audit", params={"action": "robot.move"}).json())
        assert move["who"] == "session" and move["target"] == "robot0" and "robot0" in move["detail"]["why"]
