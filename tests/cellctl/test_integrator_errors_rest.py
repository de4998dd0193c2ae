"""REST messages an integrator meets on day one: the right code, the field and the fix, no
internal function names. The app (in-process) over a store that holds an active camera + hand-eye calibration."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.handeye import RobotNoise, calibrate_handeye
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard
from cellctl.config import default_config_text
from cellctl.store import Store, sqlite_url
from tests.support.app import AppCell, in_process_cell

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, int]]:
    tmp = tmp_path_factory.mktemp("errors")
    board = Chessboard(8, 6, 30.0)
    sim = simulate_handeye("eye-in-hand", 10, np.random.default_rng(5), camera=CAM, target=board,
                           robot_noise=RobotNoise(0.05, 0.01))
    he = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, CAM, board, leave_one_out=False)
    db = tmp / "store.db"
    with Store(sqlite_url(db), "virtual-cell") as store:
        cam = store.save_calibration("camera", "cam0", None, {**CAM.to_dict(), "verdict": {"ok": True, "problems": []}},
                                     {}, "test")
        store.activate(cam.id, "test")
        store.activate(store.save_calibration("handeye", "cam0", "robot0", he.to_json(), {}, "test").id, "test")
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    with in_process_cell(tmp, config=cfg) as cell:
        yield cell, cam.id


def test_map_without_plane_height_with_an_active_handeye(served: tuple[AppCell, int]) -> None:
    s, _ = served
    with s.http() as http:
        r = http.post("/map", json={"u_px": 800, "v_px": 600})
        assert r.status_code == 422, r.text
        err = r.json()["error"]
        assert err["code"] == "plane_z_mm_required" and "plane_z_mm" in err["message"]
        assert "run" not in err["message"].split("plane_z_mm")[0]  # does not ask for calibrations we have
        r = http.post("/map", json={"u_px": 800, "v_px": 600, "plane_z_mm": 0})
        assert r.status_code == 200, r.text
        assert len(r.json()["sigma_mm"]) == 3


def test_halcon_export_needs_the_pixel_pitch(served: tuple[AppCell, int]) -> None:
    s, cam_id = served
    with s.http() as http:
        r = http.get(f"/calibrations/{cam_id}/export", params={"format": "halcon"})
        assert r.status_code == 422
        err = r.json()["error"]
        assert err["code"] == "pixel_pitch_required" and "pixel_pitch_um" in err["message"]
        # The stored camera is opencv5, which HALCON's area_scan_division cannot take: the answer
        # names the lens model to calibrate with, in REST terms (no CLI flag).
        r = http.get(f"/calibrations/{cam_id}/export", params={"format": "halcon", "pixel_pitch_um": 3.45})
        assert r.status_code == 422, r.text
        err = r.json()["error"]
        assert err["code"] == "export_unsupported"
        assert "division lens model" in err["message"] and "--" not in err["message"]


def test_unknown_recipe_names_the_route_not_a_function(served: tuple[AppCell, int]) -> None:
    s, _ = served
    with s.http() as http:
        for r in (http.get("/recipes/77"), http.post("/pick", json={"recipe_id": 77})):
            assert r.status_code == 404
            msg = r.json()["error"]["message"]
            assert "GET /recipes" in msg and "list_recipes" not in msg and "stored: none" in msg
        msg = http.get("/calibrations/999").json()["error"]["message"]
        assert "GET /calibrations" in msg and "list_calibrations" not in msg


def test_mapping_messages_name_body_fields_not_cli_flags() -> None:
    """The library names its own arguments; POST /map words the hint with its body fields, the CLI with flags."""
    from calibration.measure import MappingError, pixel_to_robot
    from cellctl.api.routes.map import FIELDS
    from cellctl.cli.map import FLAGS
    from cellctl.hints import mapping_message

    calib = {"setup": "eye-in-hand", "camera": CAM.to_dict(), "T_tool_cam": np.eye(4).tolist()}
    with pytest.raises(MappingError) as plane:
        pixel_to_robot(calib, [800, 600])
    with pytest.raises(MappingError) as pose:
        pixel_to_robot(calib, [800, 600], plane_z_mm=0.0)
    assert (plane.value.inputs, pose.value.inputs) == (("plane_z_mm",), ("robot_pose",))
    assert "--" not in str(plane.value) + str(pose.value)
    msg = mapping_message(plane.value, FIELDS)
    assert msg == "hand-eye mapping needs the working plane's height: give plane_z_mm (base frame, mm)"
    msg = mapping_message(pose.value, FIELDS)
    assert "--" not in msg and "give robot_pose_ur [x_m, y_m, z_m, rx_rad, ry_rad, rz_rad]" in msg
    assert mapping_message(plane.value, FLAGS).endswith("give --plane-z-mm Z (base frame, mm)")
