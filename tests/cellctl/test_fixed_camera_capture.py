"""A fixed camera calibrated by the routines, the robot carrying the plate (eye-to-hand).

On the built-in production cell (a camera fixed over the pick area, the plate on the tool), with
the routines' defaults and the robot at ``motion_time_scale: 0``: intrinsics-capture plans its
views for the fixed camera (``FixedCameraViewPlanner``) and ends ok, every view reachable and
good; handeye-capture on those intrinsics ends ok and finds the camera where the scene put it;
verify passes. A plate mounted off the tool centre is found on the tool and calibrated the same
way. On the fixed-camera cell, whose plate lies on the table, both routines refuse with what is
wrong instead of calibrating from views that cannot tell anything. The planner's estimates are
checked against a pinhole model with a known truth.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from cellctl.config import parse_config
from cellctl.routines.view_plan_fixed import FixedCameraViewPlanner
from cellctl.store import open_store
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld
from tests.support.app import AppCell, in_process_cell
from tests.support.forked import run_cellctl
from tests.support.served import run_job


def _config(tmp: Path, scene: str, plate_pose: list[float] | None = None) -> tuple[Path, dict[str, Any]]:
    """The built-in ``scene``'s cell.yaml with instantaneous moves (and the plate moved on the tool)."""
    text = run_cellctl("config", "default", "--scene", scene, check=True).stdout
    cfg = yaml.safe_load(text)
    scene_path = BUILTIN_SCENES[scene]
    if plate_pose is not None:
        data = yaml.safe_load(scene_path.read_text())
        data["targets"][0]["pose"] = plate_pose
        scene_path = tmp / "scene.yaml"
        scene_path.write_text(yaml.safe_dump(data))
        for group in ("cameras", "robots", "io"):
            for dev in (cfg.get(group) or {}).values():
                dev["settings"]["scene"] = str(scene_path)
    cfg["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.0
    cfg["store"]["path"] = str(tmp / "cell.db")
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path, SimWorld(load_scene(scene_path)).truth()


def _calibrate(cell: AppCell, names: tuple[str, ...]) -> dict[str, Any]:
    """Run ``names`` with their defaults, activating each calibration without force."""
    out: dict[str, Any] = {}
    with cell.http() as http:
        for name in names:
            job = run_job(http, name, {}, timeout_s=600)
            out[name] = job
            if job["state"] == "succeeded" and "calibration_id" in job["result"]:
                r = http.post(f"/calibrations/{job['result']['calibration_id']}/activate")
                out[name + " activation"] = r.status_code, r.text
    return out


@pytest.fixture(scope="module")
def production(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict[str, Any], dict[str, Any]]]:
    tmp = tmp_path_factory.mktemp("fixed-camera-capture")
    config, truth = _config(tmp, "production")
    with in_process_cell(tmp, config) as cell:
        yield _calibrate(cell, ("intrinsics-capture", "handeye-capture", "verify")), truth


def test_intrinsics_capture_ends_ok_on_the_production_cell(production: tuple[dict[str, Any], dict[str, Any]]
                                                           ) -> None:
    jobs, truth = production
    job = jobs["intrinsics-capture"]
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["verdict"]["ok"] is True, res["verdict"]
    assert jobs["intrinsics-capture activation"][0] == 200, jobs["intrinsics-capture activation"]
    # Every planned view was inside the envelope and showed the whole plate.
    assert res["views_rejected"] == 0 and res["views_used"] == 16, res
    assert res["verdict"]["coverage_missing"]["corners"] == []
    assert min(res["verdict"]["max_tilt_deg"].values()) >= 25
    K, K_true = np.array(res["K"]), np.array(truth["camera"]["K"])
    assert abs(K[0, 0] / K_true[0, 0] - 1) < 0.002 and abs(K[1, 1] / K_true[1, 1] - 1) < 0.002, K
    assert np.abs(K[:2, 2] - K_true[:2, 2]).max() < 2.0, K


def test_handeye_capture_and_verify_on_those_intrinsics(production: tuple[dict[str, Any], dict[str, Any]]) -> None:
    jobs, truth = production
    job = jobs["handeye-capture"]
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["setup"] == "eye-to-hand" and res["verdict"]["ok"] is True, res["verdict"]
    assert jobs["handeye-capture activation"][0] == 200, jobs["handeye-capture activation"]
    rot, trans = g.transform_error(np.array(res["T_base_cam"]), np.array(truth["T_base_cam"]))
    assert trans * 1e3 < 1.0 and math.degrees(rot) < 0.1, (trans * 1e3, math.degrees(rot))
    verify = jobs["verify"]
    assert verify["state"] == "succeeded" and verify["verdict_ok"] is True, verify


def test_a_plate_off_the_tool_centre_is_found_on_the_tool(tmp_path: Path) -> None:
    """60 mm towards the camera and 20 mm aside: the tilts turn about the plate, not the flange."""
    config, _ = _config(tmp_path, "production", plate_pose=[-0.01, -0.05, -0.06, 0.0, 0.0, 0.02])
    with in_process_cell(tmp_path, config) as cell:
        job = _calibrate(cell, ("intrinsics-capture",))["intrinsics-capture"]
    assert job["state"] == "succeeded", job["error"]
    assert job["result"]["verdict"]["ok"] is True and job["result"]["views_rejected"] == 0, job["result"]


def test_a_plate_lying_on_the_table_is_refused_with_the_reason(tmp_path: Path) -> None:
    """The fixed-camera cell's plate does not move with the robot: no routine view can calibrate."""
    config, truth = _config(tmp_path, "fixed-camera")
    with in_process_cell(tmp_path, config) as cell:
        first = _calibrate(cell, ("intrinsics-capture",))["intrinsics-capture"]
        with open_store(parse_config(yaml.safe_load(config.read_text()))) as store:
            cam = store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="test", note="truth")
            store.activate(cam.id, "test")
        second = _calibrate(cell, ("handeye-capture",))["handeye-capture"]
    for job in (first, second):
        assert job["state"] == "failed", job
        assert "carries neither the camera nor the plate" in job["error"], job["error"]
        assert "the plate must" in job["error"] and "bug" not in job["error"], job["error"]
    assert "mode: operator" in first["error"] and "jog-to-mark" in second["error"]


# -- the planner against a pinhole with a known truth ------------------------------------------------------
F_PX = 1400.0
SIZE = (1280, 960)
T_BASE_CAM = g.ur_pose_to_transform([0.45, 0.02, 0.5, 3.10, 0.05, 0.3])
T_TOOL_TARGET = g.ur_pose_to_transform([0.01, -0.05, -0.08, 0.05, -0.04, 0.6])
GRID = np.array([[x, y, 0.0] for y in np.arange(7) * 0.01 for x in np.arange(7) * 0.01])


def _seen(T_base_tool: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T_cam_target = g.invert(T_BASE_CAM) @ T_base_tool @ T_TOOL_TARGET
    p = g.transform_points(T_cam_target, GRID)
    uv = F_PX * p[:, :2] / p[:, 2:] + 0.5 * (np.array(SIZE) - 1)
    return uv, T_cam_target


def test_the_planner_finds_the_camera_axes_and_the_plate_on_the_tool() -> None:
    T0 = g.ur_pose_to_transform([0.44, 0.0, 0.22, math.pi, 0.0, 0.0])
    uv0, C0 = _seen(T0)
    centre = GRID.mean(axis=0)
    distance = float(g.transform_points(C0, centre[None])[0, 2])
    planner = FixedCameraViewPlanner(T0, uv0, SIZE, centre, distance, 32.0, centre_target_m=centre)
    planner.observe(T0, uv0, True, "start", C0)
    centre_base0 = g.transform_points(T0 @ T_TOOL_TARGET, centre[None])[0]
    tilts = {}
    for purpose, T in planner.plan():
        uv, C = _seen(T)
        planner.observe(T, uv, True, purpose, C)
        if purpose.startswith("tilt "):
            tilts[purpose] = (T, C)
            if len(tilts) == 4:
                break
    assert planner.R_base_cam is not None and planner.q_tool_m is not None
    err_deg = math.degrees(g.rotation_angle(planner.R_base_cam.T @ T_BASE_CAM[:3, :3]))
    assert err_deg < 0.1, err_deg
    q_true = T_TOOL_TARGET[:3, :3] @ centre + T_TOOL_TARGET[:3, 3]
    assert np.linalg.norm(planner.q_tool_m - q_true) < 1e-4, (planner.q_tool_m, q_true)
    for purpose, (T, C) in tilts.items():
        # Turned about the plate's centre: it stays where it was, and the tilt is about a camera axis.
        moved = g.transform_points(T @ T_TOOL_TARGET, centre[None])[0] - centre_base0
        assert np.linalg.norm(moved) < 1e-4, (purpose, moved)
        turn = g.matrix_to_rotvec(C[:3, :3] @ C0[:3, :3].T)
        assert math.degrees(np.linalg.norm(turn)) == pytest.approx(32.0, abs=0.01)
        assert abs(turn[2]) < 1e-6 and abs(turn[1 if purpose[5] == "x" else 0]) < 1e-6, (purpose, turn)
