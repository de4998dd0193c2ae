"""handeye-capture's station planning on the virtual cell, run as the service runs a routine.

The routine runs in a job with its motion session, against the simulated camera and robot
(instantaneous moves) and a real store; the camera calibration is the cell's true one (stored and
activated like any other), so what is measured is the stations the routine chooses and what it
does with refusals. ``test_handeye_capture.py`` runs the whole chain through the HTTP service.
"""

from __future__ import annotations

import ast
import inspect
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.handeye import HandEyeError, check_motion
from cellctl.cell import Cell
from cellctl.config import default_config_text, parse_config
from cellctl.jobs import Job, JobManager
from cellctl.routines import handeye_capture, routine, station_plan
from cellctl.routines.station_plan import pair_information
from cellctl.services import Services
from cellctl.store import open_store
from drivers.sim import world as world_module
from tests.conftest import REPO

EYE_TO_HAND_SCENE = REPO / "tests" / "data" / "scenes" / "eye-to-hand-plate-on-tool.yaml"
"""A fixed camera 0.95 m above the table looking down, the plate carried 0.12 m below the flange."""


def make_services(tmp: Path, seed: int, scene: Path | None = None, setup: str = "eye-in-hand",
                  robot: dict[str, Any] | None = None, camera: bool = True) -> Services:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    for dev in (data["cameras"]["cam0"], data["robots"]["robot0"]):
        dev["settings"]["seed"] = seed
        dev["settings"]["scene"] = None if scene is None else str(scene)
    data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.0  # the stations, not the travel, are tested
    data["robots"]["robot0"].update(robot or {})
    data["calibration"]["setup"] = setup
    config = parse_config(data)
    key = (str(scene.resolve()) if scene else "built-in", seed)
    world_module._WORLDS.pop(key, None)  # a fresh world: the robot starts at home
    svc = Services(config, Cell(config), open_store(config), JobManager())
    if camera:
        truth = world_module.world_for(scene, seed).truth()
        cam = svc.store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="test", note="truth")
        svc.store.activate(cam.id, "test")
    return svc


@pytest.fixture()
def tmp_services(tmp_path: Path) -> Iterator[list[Services]]:
    made: list[Services] = []
    yield made
    for svc in made:
        svc.close()


def run_capture(svc: Services, params: dict[str, Any], timeout_s: float = 600.0) -> Job:
    """Start handeye-capture as the service does (the job owns the robot's motion) and wait for it."""
    robot = svc.cell.robot("robot0").ensure_open()
    motion = (robot, robot.motion.begin("test", "routine handeye-capture"))
    module = routine("handeye-capture")
    job = svc.jobs.start("handeye-capture", lambda ctx: module.run(svc, ctx), params, "test", motion)
    return svc.jobs.join(job.id, timeout_s)


def moved_poses(svc: Services) -> list[np.ndarray]:
    return [g.ur_pose_to_transform(a.detail["pose_ur"]) for a in svc.store.audit_log(limit=500, action="robot.move")
            if a.result == "ok"]


def test_eye_to_hand_stations_end_with_the_verdict_ok(tmp_path: Path, tmp_services: list[Services]) -> None:
    scene = EYE_TO_HAND_SCENE
    svc = make_services(tmp_path, 21, scene, "eye-to-hand")
    tmp_services.append(svc)
    job = run_capture(svc, {})
    assert job.state == "succeeded", job.error
    res = job.result
    assert res is not None
    assert res["setup"] == "eye-to-hand" and res["complete"] is True and res["verdict"]["ok"] is True
    assert res["coverage"]["missing"] == [] and res["stations_used"] >= 10
    truth = world_module.world_for(scene, 21).truth()
    rot, trans = g.transform_error(np.array(res["T_base_cam"]), np.array(truth["T_base_cam"]))
    sig = res["uncertainty"]
    assert trans * 1e3 < max(4 * sig["trans_mm"], 0.2), (trans * 1e3, sig)
    assert math.degrees(rot) < max(4 * sig["rot_deg"], 0.05), (math.degrees(rot), sig)


def test_poses_outside_the_envelope_are_left_out_and_the_verdict_is_ok(
        tmp_path: Path, tmp_services: list[Services]) -> None:
    # The start pose is at z = 550 mm: every station that backs away from the plate is out of reach.
    svc = make_services(tmp_path, 22, robot={"envelope": {"x_mm": [100.0, 800.0], "y_mm": [-400.0, 400.0],
                                                          "z_mm": [2.0, 560.0]}})
    tmp_services.append(svc)
    job = run_capture(svc, {})
    assert job.state == "succeeded", job.error
    res = job.result
    assert res is not None
    assert res["complete"] is True, res["coverage"]
    left = res["candidates_left_out"]
    assert any("outside the workspace envelope" in k and "z = N mm" in k for k in left), left
    for T in moved_poses(svc):
        assert T[2, 3] <= 0.560 + 1e-9


def test_a_move_the_robot_refuses_is_skipped_with_its_reason(tmp_path: Path, tmp_services: list[Services]) -> None:
    # At 0.02 m/s a move may be at most 0.24 m long (12 s): the robot refuses the longer ones itself.
    svc = make_services(tmp_path, 23, robot={"max_move_duration_s": 12.0})
    tmp_services.append(svc)
    job = run_capture(svc, {"speed_m_s": 0.02, "max_stations": 30})
    assert job.state == "succeeded", job.error
    res = job.result
    assert res is not None
    assert res["stations_refused"], "no move was refused: the test no longer tests a refusal"
    assert all("would take" in r["reason"] and r["station"] for r in res["stations_refused"])
    assert res["stations_tried"] == res["stations_used"] + res["stations_rejected"] + len(res["stations_refused"])
    assert res["verdict"]["ok"] is True


def test_a_spent_budget_says_what_is_missing(tmp_path: Path, tmp_services: list[Services]) -> None:
    # Tilts of 5 deg and no spin: no relative rotation reaches the 15 deg the checks ask for.
    svc = make_services(tmp_path, 24)
    tmp_services.append(svc)
    job = run_capture(svc, {"max_tilt_deg": 5, "max_spin_deg": 0, "stations": 5, "max_stations": 6})
    assert job.state == "succeeded", job.error
    res = job.result
    assert res is not None
    assert res["stations_tried"] == 6 and res["complete"] is False
    missing = res["coverage"]["missing"]
    assert any(m.startswith("rotation about two axes") for m in missing), missing
    assert res["verdict"]["coverage_missing"] == missing
    stored = svc.store.get_calibration(res["calibration_id"]).result
    assert stored["verdict"]["coverage_missing"] == missing
    problem = [q for q in stored["verdict"]["problems"] if q["code"] == "coverage_missing"]
    assert len(problem) == 1 and "max_stations" in problem[0]["message"] and problem[0]["severity"] == "warning"


def test_stations_over_the_budget_and_no_camera_are_clear_errors(tmp_path: Path,
                                                                   tmp_services: list[Services]) -> None:
    svc = make_services(tmp_path, 25, camera=False)
    tmp_services.append(svc)
    job = run_capture(svc, {"stations": 12, "max_stations": 8})
    assert job.state == "failed" and "raise max_stations or lower stations" in (job.error or "")
    job = run_capture(svc, {})
    assert job.state == "failed"
    assert "no active calibration" in (job.error or "") and "POST /routines/intrinsics-capture" in (job.error or "")
    assert svc.store.list_calibrations(kind="handeye") == []


def test_no_message_names_a_cli_command() -> None:
    """Every string of the routine's modules is CLI-free."""
    for module in (handeye_capture, station_plan):
        tree = ast.parse(inspect.getsource(module))
        texts = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
        assert len(texts) > 10
        for text in texts:
            assert not re.search(r"`cellctl|cellctl (calib|job)|--[a-z]", text), (module.__name__, text)


def test_solver_advice_reaches_rest_callers_without_cli_options() -> None:
    # Stations rotating about the base z axis only: the solver refuses and names a CLI option.
    X = g.make_transform(g.rotvec_to_matrix([0.01, -0.02, 0.03]), [0.05, 0.0, 0.02])
    Z = g.make_transform(g.rotvec_to_matrix([math.pi, 0, 0]), [0.3, 0.1, 0.0])
    G = [g.make_transform(g.rotvec_to_matrix([0, 0, math.radians(a)]) @ g.rotvec_to_matrix([math.pi, 0, 0]),
                          [0.4, 0.0, 0.5]) for a in (0, 20, 40, 60)]
    C = [g.invert(X) @ g.invert(Gi) @ Z for Gi in G]
    with pytest.raises(HandEyeError) as err:
        check_motion("eye-in-hand", G, C)
    said = str(err.value)  # the library's words: what is wrong and its fix, no front end's command
    assert "cellctl" not in said and "--" not in said and err.value.alternative == "dof4"
    assert "rotate 15-30 deg about a second axis" in said
    assert "dof 4 and target_z_mm" in handeye_capture.DOF4_HINT  # the routine's way to the 4-DOF solver


def test_pair_information_sees_only_rotation_across_its_axis() -> None:
    shift = g.make_transform(np.eye(3), [0.1, 0.0, 0.0])
    assert np.allclose(pair_information(shift), 0.0)  # a translation says nothing about the hand-eye
    turn = g.make_transform(g.rotvec_to_matrix([0, 0, math.radians(30)]), [0.0, 0.0, 0.0])
    M = pair_information(turn)
    w = np.linalg.eigvalsh(M)
    assert w[0] == pytest.approx(0.0, abs=1e-12)  # nothing along the rotation axis
    assert w[1] == pytest.approx(4 * math.sin(math.radians(15)) ** 2) and w[2] == pytest.approx(w[1])
    assert np.allclose(M @ [0, 0, 1], 0.0)


def test_the_camera_covariance_is_read_in_the_handeye_order() -> None:
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"]  # k3 fixed: not in the calibration's parameters
    cov = np.diag(np.arange(1.0, 9.0))
    full = handeye_capture.camera_covariance({"parameters": {"names": names, "covariance": cov.tolist()}},
                                             "opencv5")
    assert full is not None and full.shape == (9, 9)
    assert np.allclose(np.diag(full), [1, 2, 3, 4, 5, 6, 7, 8, 0])
    assert handeye_capture.camera_covariance({}, "opencv5") is None  # e.g. a camera file without one
    bad = {"parameters": {"names": ["fx", "kappa"], "covariance": np.eye(2).tolist()}}
    assert handeye_capture.camera_covariance(bad, "opencv5") is None
