"""All four routines to completion on ``cellctl serve`` (virtual cell), checked against truth.

One served process for the module: intrinsics-capture → activate → handeye-capture → activate →
verify → jog-to-mark (the test plays the operator: it jogs the robot onto each mark's true
position over the API and presses record) → activate → /map. The robot moves at 5x real time
(``motion_time_scale: 0.2``): the routines, not the travel, are tested here, yet a move still
takes time, so a cancel lands mid-routine (real-time motion: the README tour, the operator page).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.targets import target_from_dict
from cellctl.config import default_config_text
from tests.conftest import Served, start_served, stop_served
from tests.support.forked import run_cellctl
from tests.support.served import run_job


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    tmp = tmp_path_factory.mktemp("routines")
    data = yaml.safe_load(default_config_text())
    data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.2
    (tmp / "cell.yaml").write_text(yaml.safe_dump(data))
    s = start_served(tmp, tmp / "cell.yaml")
    try:
        yield s
    finally:
        stop_served(s)


@pytest.fixture(scope="module")
def truth() -> dict[str, Any]:
    out = run_cellctl("sim", "truth", check=True).stdout
    return dict(json.loads(out))


HOME_POSE = {"x_m": 0.40, "y_m": 0.0, "z_m": 0.55, "rx_rad": np.pi, "ry_rad": 0.0, "rz_rad": 0.0}


def go_home(http: httpx.Client) -> None:
    """Back to the start pose, where the whole plate is in view (a cancelled routine stops anywhere)."""
    r = http.post("/robots/robot0/move", json={"pose_ur": HOME_POSE, "speed_m_s": 0.2})
    assert r.status_code == 200, r.text



@pytest.fixture(scope="module")
def calibrated(served: Served) -> dict[str, Any]:
    """Runs intrinsics-capture and handeye-capture once, activating both."""
    out: dict[str, Any] = {}
    with served.client(timeout_s=60) as http:
        job = run_job(http, "intrinsics-capture", {"views": 12})
        assert job["state"] == "succeeded", job["error"]
        out["intrinsics"] = job["result"]
        # A short capture's verdict may be not ok; activation then needs force (INTERFACES §5).
        force = {"force": not (job["result"].get("verdict") or {}).get("ok", True)}
        assert http.post(f"/calibrations/{job['result']['calibration_id']}/activate", json=force).status_code == 200
        job = run_job(http, "handeye-capture", {"stations": 10})
        assert job["state"] == "succeeded", job["error"]
        out["handeye"] = job["result"]
        force = {"force": not (job["result"].get("verdict") or {}).get("ok", True)}
        assert http.post(f"/calibrations/{job['result']['calibration_id']}/activate", json=force).status_code == 200
    return out


def test_intrinsics_capture_recovers_the_camera(calibrated: dict[str, Any], truth: dict[str, Any]) -> None:
    res = calibrated["intrinsics"]
    K, K_true = np.array(res["K"]), np.array(truth["camera"]["K"])
    assert res["views_used"] >= 6
    assert res["rms_px"] < 0.1
    assert abs(K[0, 0] - K_true[0, 0]) < 3.0 and abs(K[1, 1] - K_true[1, 1]) < 3.0
    assert abs(K[0, 2] - K_true[0, 2]) < 3.0 and abs(K[1, 2] - K_true[1, 2]) < 3.0
    assert res["activated"] is False


def test_the_report_counts_the_views_as_the_job_did(served: Served, calibrated: dict[str, Any]) -> None:
    """The job's views_rejected (shots the capture dropped before calibrating) is the report's."""
    res = calibrated["intrinsics"]
    with served.client(timeout_s=60) as http:
        figures = http.get(f"/calibrations/{res['calibration_id']}/report", params={"format": "json"}).json()
        page = http.get(f"/calibrations/{res['calibration_id']}/report").text
    tried = res["views_used"] + res["views_rejected"]
    assert figures["capture"] == {"views_tried": tried, "views_rejected": res["views_rejected"]}
    assert f"<td class='num'>{tried} / {res['views_rejected']}</td>" in page


def test_handeye_capture_recovers_T_tool_cam(calibrated: dict[str, Any], truth: dict[str, Any]) -> None:
    res = calibrated["handeye"]
    rot, trans = g.transform_error(np.array(res["T_tool_cam"]), np.array(truth["T_tool_cam"]))
    sig = res["uncertainty"]
    # Within 4 sigma of the reported uncertainty, and absolutely small.
    assert trans * 1e3 < max(4 * sig["trans_mm"], 0.2), (trans * 1e3, sig)
    assert np.degrees(rot) < max(4 * sig["rot_deg"], 0.05), (np.degrees(rot), sig)


def test_verify_passes_with_active_calibrations(served: Served, calibrated: dict[str, Any]) -> None:
    with served.client() as http:
        go_home(http)
        job = run_job(http, "verify", {})
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["passed"] is True
    assert res["handeye_calibration_id"] == calibrated["handeye"]["calibration_id"]
    assert res["camera_source"] == "handeye"  # measured through the camera the hand-eye maps through
    assert res["drift_px"] < 0.5 and res["drift_mm"] < 0.3


def test_jog_to_mark_and_map(served: Served, calibrated: dict[str, Any], truth: dict[str, Any]) -> None:
    plate = truth["targets"]["plate"]
    target = target_from_dict(plate["target"])
    pts = target.points()
    T_base_target = np.array(plate["T_base_target"])
    with served.client(timeout_s=60) as http:
        go_home(http)
        home = http.get("/robots/robot0/state").json()["T_base_tool"]
        r = http.post("/routines/jog-to-mark", json={"marks": 9})
        assert r.status_code == 202
        job_id = r.json()["id"]
        for step in range(1, 10):
            deadline = time.monotonic() + 30
            # the previous mark's request may still show for a moment after its record
            while ((job := http.get(f"/jobs/{job_id}").json())["waiting_for"] or {}).get("step") != step:
                assert job["state"] == "running", job["error"]
                assert time.monotonic() < deadline
                time.sleep(0.1)
            mark = job["waiting_for"]
            p_base = g.transform_points(T_base_target, pts.xyz_m[list(pts.ids).index(mark["mark_id"])])[0]
            # The operator jogs the tool tip onto the mark (tool pointing down, 5 mm above it)...
            pose = {"x_m": p_base[0], "y_m": p_base[1], "z_m": p_base[2] + 0.005, "rx_rad": np.pi, "ry_rad": 0.0,
                    "rz_rad": 0.0}
            assert http.post("/robots/robot0/move", json={"pose_ur": pose, "speed_m_s": 0.2}).status_code == 200
            # ...and presses record.
            assert http.post(f"/jobs/{job_id}/record").status_code == 200
        deadline = time.monotonic() + 30
        while (job := http.get(f"/jobs/{job_id}").json())["state"] == "running":
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert job["state"] == "succeeded", job["error"]
        res = job["result"]
        # Robot repeatability is 0.02 mm: the fitted map is that good.
        assert res["rms_mm"] < 0.1
        assert res["verdict"]["ok"] is True, res["verdict"]
        assert http.post(f"/calibrations/{res['calibration_id']}/activate").status_code == 200
        report = http.get(f"/calibrations/{res['calibration_id']}/report").text
        assert "npoint calibration" in report and "Verdict: OK" in report  # calibration/npoint/verdict.py
        assert "Residual per mark" in report and "<svg" in report  # the N-point page has its own plots
        # Back to the capture pose, then map a mark's pixel and compare with its true position.
        assert http.post("/robots/robot0/move", json={"T_base_tool": home, "speed_m_s": 0.2}).status_code == 200
        m = res["pairs"][4]
        p_true = g.transform_points(T_base_target, pts.xyz_m[list(pts.ids).index(m["mark_id"])])[0] * 1e3
        r = http.post("/map", json={"u_px": m["u_px"], "v_px": m["v_px"], "calibration": "npoint"})
        assert r.status_code == 200, r.text
        out = r.json()
        assert out["calibration_kind"] == "npoint" and out["warning"] is None
        assert np.hypot(out["x_mm"] - p_true[0], out["y_mm"] - p_true[1]) < 0.2
        # The hand-eye route maps the same pixel onto the plate plane.
        r = http.post("/map", json={"u_px": m["u_px"], "v_px": m["v_px"], "plane_z_mm": p_true[2],
                                    "calibration": "handeye"})
        assert r.status_code == 200, r.text
        out = r.json()
        assert out["calibration_kind"] == "handeye"
        assert np.hypot(out["x_mm"] - p_true[0], out["y_mm"] - p_true[1]) < 0.5
        assert all(s > 0 for s in out["sigma_mm"][:2])


def test_sse_progress_arrives(served: Served, calibrated: dict[str, Any]) -> None:
    with served.client(timeout_s=60) as http:
        go_home(http)
        job_id = http.post("/routines/verify", json={}).json()["id"]
        kinds = []
        with http.stream("GET", f"/jobs/{job_id}/events") as stream:
            assert stream.headers["content-type"].startswith("text/event-stream")
            for line in stream.iter_lines():
                if line.startswith("event: "):
                    kinds.append(line[7:])
    assert "progress" in kinds and kinds[-1] == "state"


def test_cancel_mid_routine_stops_robot_and_stores_nothing(served: Served, calibrated: dict[str, Any]) -> None:
    with served.client(timeout_s=60) as http:
        before = http.get("/calibrations").json()
        job_id = http.post("/routines/intrinsics-capture", json={"views": 16}).json()["id"]
        deadline = time.monotonic() + 60
        while http.get(f"/jobs/{job_id}").json()["progress"] < 0.15:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert http.delete(f"/jobs/{job_id}").status_code == 200
        while (job := http.get(f"/jobs/{job_id}").json())["state"] == "running":
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert job["state"] == "cancelled"
        assert http.get("/calibrations").json() == before
        state = http.get("/robots/robot0/state").json()
        assert state["moving"] is False
        audit = http.get("/audit", params={"action": "routine.cancel"}).json()
        assert any(a["detail"]["job_id"] == job_id for a in audit)


def test_routine_bad_params_are_422(served: Served) -> None:
    with served.client() as http:
        r = http.post("/routines/intrinsics-capture", json={"views": "many"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_params"
        r = http.post("/routines/dance", json={})
        assert r.status_code == 404 and r.json()["error"]["code"] == "unknown_routine"


def test_move_outside_envelope_is_refused_and_audited(served: Served) -> None:
    with served.client() as http:
        before = http.get("/robots/robot0/state").json()["T_base_tool"]
        r = http.post("/robots/robot0/move", json={"pose_ur": {"x_m": 2.0, "y_m": 0, "z_m": 0.3, "rx_rad": 3.14,
                                                               "ry_rad": 0, "rz_rad": 0}})
        assert r.status_code == 422 and r.json()["error"]["code"] == "motion_rejected"
        assert "outside the workspace envelope" in r.json()["error"]["message"]
        after = http.get("/robots/robot0/state").json()["T_base_tool"]
        assert np.allclose(before, after, atol=1e-3)
        audit = http.get("/audit", params={"action": "robot.move"}).json()
        assert audit[0]["result"].startswith("refused")


def test_cli_job_run_follow(served: Served, calibrated: dict[str, Any]) -> None:
    with served.client() as http:
        go_home(http)
    r = run_cellctl("job", "run", "verify", "--follow", "--url", served.base_url,
                    "--token", served.token, "--param", "tolerance_px=2.0", timeout=120)
    assert r.returncode == 0, r.stderr
    job = json.loads(r.stdout)
    assert job["state"] == "succeeded" and job["result"]["tolerance_px"] == 2.0
    assert "100.0%" in r.stderr and "succeeded" in r.stderr


def test_cli_job_run_exits_non_zero_when_the_routine_is_refused(served: Served) -> None:
    """A target the config lacks is refused at once (422, no job): exit 2, one line naming it."""
    r = run_cellctl("job", "run", "verify", "--follow", "--url", served.base_url,
                    "--token", served.token, "--param", "target=nosuch", timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert "no target 'nosuch'" in r.stderr


def test_cli_job_run_bad_token_is_one_line_error(served: Served) -> None:
    r = run_cellctl("job", "run", "verify", "--url", served.base_url, "--token", "nope", timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "401" in r.stderr
