"""Every mapping goes through the camera the hand-eye was solved with (issue 26 item 1).

The virtual cell's data (calibration.synthetic, with truth): an eye-in-hand hand-eye started from
a stale camera file (fx 1 % high) and solved with the intrinsics refined jointly. The store holds
the stale camera calibration (active) and the hand-eye (active); the service's mapping (``POST
/map``, the pick poses through ``active_mapping``) must land on the truth, where mapping through the
stale camera (what the service did before) misses by millimetres. Activating a camera calibration
that differs from the hand-eye's answers a warning that the hand-eye must be redone (409
``handeye_camera_mismatch`` unless forced when the hand-eye carries no camera, as its mapping would
change), and ``cellctl map --camera`` refuses a camera other than the hand-eye's.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import transform_to_ur_pose
from calibration.handeye import HandEyeResult, RobotNoise, calibrate_handeye
from calibration.io import camera_difference_px, camera_mismatch
from calibration.measure import map_handeye
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard
from cellctl.config import default_config_text
from cellctl.mapping import active_mapping
from cellctl.pick.flow import Recipe
from cellctl.pick.model import teach
from cellctl.pick.pose import pick_pose
from cellctl.store import Store, sqlite_url
from tests.support.app import AppCell, in_process_cell
from tests.support.cli import run_cli

TRUE_CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                       np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
STALE_K = TRUE_CAM.K.copy()
STALE_K[0, 0] *= 1.01  # the camera file the hand-eye starts from: fx 1 % high
STALE = CameraModel("opencv5", 1600, 1200, STALE_K, TRUE_CAM.dist.copy())
BOARD = Chessboard(8, 6, 30.0)
# Pixels where a 1 % fx error matters (edges, corners) and the centre.
PIXELS = ((1500.0, 1100.0), (100.0, 150.0), (800.0, 600.0))
OWN_TOLERANCE_MM = 0.3
"""The hand-eye's own mapping on noise-free query pixels: robot noise 0.05 mm / 0.01°, 12 stations."""
STALE_MISS_MM = 1.0
"""Through the stale camera the edge pixels miss by ~2 mm (measured 1.7-2.3 mm on two seeds)."""


@dataclass
class Cell:
    app: AppCell
    he: HandEyeResult
    T_base_tool: np.ndarray
    T_base_cam_true: np.ndarray
    ids: dict[str, int]


def _truth_on_plane(T_base_cam: np.ndarray, uv: tuple[float, float], depth_m: float = 0.45) -> np.ndarray:
    """The base-frame point (m) the true camera sees at pixel ``uv``, ``depth_m`` in front of it."""
    ray = TRUE_CAM.unproject(np.array([uv]))[0]
    return np.asarray(T_base_cam[:3, :3] @ (ray / ray[2] * depth_m) + T_base_cam[:3, 3])


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    sim = simulate_handeye("eye-in-hand", 12, np.random.default_rng(5), camera=TRUE_CAM, target=BOARD,
                           robot_noise=RobotNoise(0.05, 0.01))
    he = calibrate_handeye("eye-in-hand", sim.G_recorded, sim.detections, STALE, BOARD, leave_one_out=False,
                           refine_intrinsics=True)
    tmp = tmp_path_factory.mktemp("own_camera")
    db = tmp / "store.db"
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    ok = {"verdict": {"ok": True, "problems": []}}
    with Store(sqlite_url(db), "virtual-cell") as store:
        stale = store.save_calibration("camera", "cam0", None, {**STALE.to_dict(), **ok}, {}, "test")
        store.activate(stale.id, "test")
        other_K = TRUE_CAM.K.copy()
        other_K[1, 1] *= 1.02
        other = store.save_calibration("camera", "cam0", None, {**CameraModel(
            "opencv5", 1600, 1200, other_K, TRUE_CAM.dist.copy()).to_dict(), **ok}, {}, "test")
        assert he.camera is not None
        own = store.save_calibration("camera", "cam0", None, {**he.camera.to_dict(), **ok}, {}, "test")
        he_json = {**he.to_json(), "camera_calibration_id": stale.id}
        he_json["verdict"]["ok"] = True
        he_rec = store.save_calibration("handeye", "cam0", "robot0", he_json, {}, "test")
        store.activate(he_rec.id, "test")
        ids = {"stale": stale.id, "other": other.id, "own": own.id, "handeye": he_rec.id}
    G = sim.G_true[3]
    with in_process_cell(tmp, config=cfg) as app:
        yield Cell(app, he, G, G @ sim.X_true, ids)


def test_the_hand_eye_refined_the_stale_camera_and_carries_both(cell: Cell) -> None:
    he = cell.he.to_json()
    assert he["intrinsics_refined"] is True
    own, start = CameraModel.from_dict(he["camera"]), CameraModel.from_dict(he["camera_initial"])
    assert abs(own.fx / TRUE_CAM.fx - 1) < 2e-3  # the 1 % error is gone
    assert camera_difference_px(start, STALE) < 1e-5  # px (the ray round trip iterates)
    assert camera_mismatch(own, STALE, "the stale camera") is not None


def test_the_service_maps_through_the_hand_eyes_camera(cell: Cell) -> None:
    pose = transform_to_ur_pose(cell.T_base_tool).tolist()
    stale_miss = []
    with cell.app.http() as http:
        for uv in PIXELS:
            P_mm = _truth_on_plane(cell.T_base_cam_true, uv) * 1e3
            r = http.post("/map", json={"u_px": uv[0], "v_px": uv[1], "plane_z_mm": float(P_mm[2]),
                                        "robot_pose_ur": pose})
            assert r.status_code == 200, r.text
            a = r.json()
            assert a["calibration_kind"] == "handeye" and a["calibration_id"] == cell.ids["handeye"]
            got = np.array([a["x_mm"], a["y_mm"], a["z_mm"]])
            assert np.linalg.norm(got - P_mm) < OWN_TOLERANCE_MM, (uv, got - P_mm)
            # what mapping through the active (stale) camera calibration gives: millimetres off
            stale = map_handeye(cell.he.to_json(), np.array(uv), STALE, float(P_mm[2]), cell.T_base_tool)
            stale_miss.append(float(np.linalg.norm(stale.xyz_mm - P_mm)))
    assert max(stale_miss) > STALE_MISS_MM, stale_miss


def test_the_pick_pose_lands_on_the_truth(cell: Cell) -> None:
    services = cell.app.client.app.state.services  # type: ignore[attr-defined]
    mapping = active_mapping(services, "cam0", "robot0")
    assert mapping.camera_source == "handeye" and mapping.camera_calibration_id == cell.ids["stale"]
    image = np.full((240, 320), 40, np.uint8)
    cv2.rectangle(image, (100, 80), (220, 150), 220, -1)
    model = teach(image, (80, 60, 160, 110), mode="shape", name="plate")
    uv = PIXELS[0]
    P = _truth_on_plane(cell.T_base_cam_true, uv)
    recipe = Recipe(name="plate", models=[model.to_dict()], plane_z_mm=float(P[2] * 1e3), grasp_z_mm=0.0)
    pp = pick_pose(mapping, recipe, uv[0], uv[1], 0.0, cell.T_base_tool, 0.0)
    assert np.linalg.norm(pp["T_pick"][:3, 3] - P) * 1e3 < OWN_TOLERANCE_MM


def test_activating_a_different_camera_says_the_hand_eye_must_be_redone(cell: Cell) -> None:
    pose = transform_to_ur_pose(cell.T_base_tool).tolist()
    uv = PIXELS[0]
    P_mm = _truth_on_plane(cell.T_base_cam_true, uv) * 1e3
    with cell.app.http() as http:
        # the hand-eye carries its camera: the new intrinsics are activated (recalibrating starts with
        # them), the answer says the hand-eye must be redone, and the mapping does not move
        r = http.post(f"/calibrations/{cell.ids['other']}/activate")
        assert r.status_code == 200, r.text
        warning = r.json()["warning"]
        assert "hand-eye must be redone" in warning and f"hand-eye calibration {cell.ids['handeye']}" in warning
        assert "keeps mapping through the camera it was solved with" in warning
        r = http.post("/map", json={"u_px": uv[0], "v_px": uv[1], "plane_z_mm": float(P_mm[2]), "robot_pose_ur": pose})
        got = np.array([r.json()[k] for k in ("x_mm", "y_mm", "z_mm")])
        assert np.linalg.norm(got - P_mm) < OWN_TOLERANCE_MM
        # the one it started from (its camera_calibration_id) and its own camera stored as a camera
        # calibration are the same camera: no warning
        for key in ("stale", "own"):
            r = http.post(f"/calibrations/{cell.ids[key]}/activate")
            assert r.status_code == 200 and r.json()["warning"] is None, r.text
        # a hand-eye file without a camera of its own would map through the new intrinsics: refused
        he_json = cell.he.to_json()
        for key in ("camera", "camera_initial"):
            he_json.pop(key)
        he_json["intrinsics_refined"] = False  # an older file, solved with fixed intrinsics
        he_json["verdict"]["ok"] = True
        r = http.post("/calibrations", json={**he_json, "camera_calibration_id": cell.ids["stale"]})
        assert r.status_code == 201, r.text
        assert http.post(f"/calibrations/{r.json()['id']}/activate").status_code == 200
        r = http.post(f"/calibrations/{cell.ids['other']}/activate")
        assert r.status_code == 409, r.text
        err = r.json()["error"]
        assert err["code"] == "handeye_camera_mismatch" and "carries no camera of its own" in err["message"]
        assert '"force": true' in err["message"]
        assert http.get(f"/calibrations/{cell.ids['own']}").json()["active"] is True  # nothing changed
        r = http.post(f"/calibrations/{cell.ids['other']}/activate", json={"force": True})
        assert r.status_code == 200 and "hand-eye must be redone" in r.json()["warning"], r.text
        forced = [e for e in http.get("/audit").json() if e["action"] == "calibration.force_activate"]
        assert forced and "handeye_camera_mismatch" in forced[-1]["detail"]


def _write(path: Path, data: dict[str, Any]) -> str:
    path.write_text(json.dumps(data))
    return str(path)


def test_cellctl_map_refuses_another_camera(cell: Cell, tmp_path: Path) -> None:
    he = _write(tmp_path / "he.json", cell.he.to_json())
    stale = _write(tmp_path / "stale.json", STALE.to_dict())
    assert cell.he.camera is not None
    rounded = cell.he.camera.to_dict()
    rounded["K"] = np.round(np.asarray(rounded["K"]), 4).tolist()  # a copy with rounded numbers: the same camera
    own = _write(tmp_path / "own.json", rounded)
    uv = PIXELS[0]
    P_mm = _truth_on_plane(cell.T_base_cam_true, uv) * 1e3
    pose = ",".join(repr(float(v)) for v in transform_to_ur_pose(cell.T_base_tool))
    args = ["--plane-z-mm", repr(float(P_mm[2])), "--robot-pose", pose, "--pixel-sigma-px", "0", repr(uv[0]),
            repr(uv[1])]
    r = run_cli("map", "--calib", he, "--camera", stale, *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "carries the camera it was solved with" in lines[0] and "fx" in lines[0], r.stderr
    for extra in ([], ["--camera", own]):
        r = run_cli("map", "--calib", he, *extra, *args)
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        assert np.linalg.norm(np.array([out["x_mm"], out["y_mm"], out["z_mm"]]) - P_mm) < OWN_TOLERANCE_MM


def test_a_hand_eye_file_that_refined_the_intrinsics_must_carry_its_camera(cell: Cell) -> None:
    he = cell.he.to_json()
    he.pop("camera")
    with cell.app.http() as http:
        r = http.post("/calibrations", json=he)
        assert r.status_code == 422, r.text
        message = r.json()["error"]["message"]
        assert "intrinsics_refined" in message and "carries no camera" in message
        bad = {**cell.he.to_json(), "camera_initial": {"model": "opencv5"}}
        r = http.post("/calibrations", json=bad)
        assert r.status_code == 422 and "camera_initial" in r.json()["error"]["message"], r.text


def test_a_hand_eye_alone_asks_for_the_plane_height(cell: Cell, tmp_path: Path) -> None:
    """No camera calibration active: the hand-eye maps through its own camera, so a request without
    plane_z_mm is told to give it (422), not that no calibration maps (409)."""
    db = tmp_path / "store.db"
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    he_json = cell.he.to_json()
    he_json["verdict"]["ok"] = True
    with Store(sqlite_url(db), "virtual-cell") as store:
        store.activate(store.save_calibration("handeye", "cam0", "robot0", he_json, {}, "test").id, "test")
    pose = transform_to_ur_pose(cell.T_base_tool).tolist()
    with in_process_cell(tmp_path, config=cfg) as app, app.http() as http:
        r = http.post("/map", json={"u_px": 800, "v_px": 600, "robot_pose_ur": pose})
        assert r.status_code == 422 and r.json()["error"]["code"] == "plane_z_mm_required", r.text
        r = http.post("/map", json={"u_px": 800, "v_px": 600, "plane_z_mm": 0.0, "robot_pose_ur": pose})
        assert r.status_code == 200 and r.json()["calibration_kind"] == "handeye", r.text
