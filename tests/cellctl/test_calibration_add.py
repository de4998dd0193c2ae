"""``POST /calibrations`` and ``cellctl store add``: a calibration file made elsewhere enters the store.

The files are made by the calibration package's own solvers (as the CLI writes them): a camera
(cam.json, with and without a verdict, as ``calib import`` writes it), a 6-DOF and a 4-DOF hand-eye
(he.json) and an n-point map (np.json). Each is stored as a new, inactive version; garbage and
files of another kind answer 422 saying what was wrong and what to give.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.handeye import calibrate_handeye, calibrate_handeye_dof4
from calibration.npoint import fit_npoint
from calibration.synthetic import simulate_handeye, simulate_scara
from calibration.targets import Chessboard
from tests.support.app import AppCell, in_process_cell
from tests.support.cli import run_cli

CAM = CameraModel("opencv5", 1280, 1024, np.array([[1400.0, 0, 640], [0, 1400, 512], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(7, 5, 25.0)


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = json.loads(json.dumps(d, default=lambda o: o.tolist() if hasattr(o, "tolist") else float(o)))
    return out


@pytest.fixture(scope="module")
def files() -> dict[str, dict[str, Any]]:
    cam = {**CAM.to_dict(), "rms_px": 0.12, "views": [], "verdict": {"ok": True, "problems": []}}
    imported = {**CAM.to_dict(), "imported_from": "camera.yaml"}  # what `calib import` writes: no verdict
    s = simulate_handeye("eye-in-hand", 10, np.random.default_rng(1), camera=CAM, target=BOARD)
    he6 = calibrate_handeye("eye-in-hand", s.G_recorded, s.detections, CAM, BOARD, leave_one_out=False).to_json()
    sc = simulate_scara("eye-in-hand", 10, np.random.default_rng(2), camera=CAM, target=BOARD)
    he4 = calibrate_handeye_dof4("eye-in-hand", sc.G_recorded, sc.detections, CAM, BOARD, sc.target_z_mm,
                                 leave_one_out=False).to_json()
    uv = np.array([[u, v] for u in (100.0, 600, 1100) for v in (100.0, 500, 900)])
    xy = uv * 0.2 + [300.0, -50.0]
    npj = fit_npoint(uv, xy, "affine").to_json()
    return {"camera": cam, "imported": imported, "handeye": _jsonable(he6), "handeye4": _jsonable(he4),
            "npoint": _jsonable(npj)}


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AppCell]:
    with in_process_cell(tmp_path_factory.mktemp("caladd")) as a:
        yield a


@pytest.mark.parametrize("name,kind,robot", [("camera", "camera", None), ("imported", "camera", None),
                                              ("handeye", "handeye", "robot0"), ("handeye4", "handeye", "robot0"),
                                              ("npoint", "npoint", "robot0")])
def test_a_good_file_of_each_kind_is_stored_inactive(app: AppCell, files: dict[str, Any], name: str, kind: str,
                                                     robot: str | None) -> None:
    before = app.client.get("/calibrations", params={"kind": kind}, headers=app.auth()).json()
    r = app.client.post("/calibrations", json=files[name], params={"note": f"test {name}"}, headers=app.auth())
    assert r.status_code == 201, r.text
    out = r.json()
    assert out["kind"] == kind and out["camera_id"] == "cam0" and out["robot_id"] == robot
    assert out["activated"] is False and out["active"] is False and out["note"] == f"test {name}"
    assert out["version"] == len(before) + 1
    assert out["verdict_ok"] is (files[name].get("verdict") or {}).get("ok")
    if "verdict" not in files[name]:  # calib import and calib npoint write none
        assert "no verdict" in out["notes"][0]
    stored = app.client.get(f"/calibrations/{out['id']}", headers=app.auth()).json()
    assert stored["result"] == files[name] and stored["active"] is False
    if name == "handeye4":
        assert stored["result"]["dof"] == 4


def test_the_kind_and_devices_can_be_named(app: AppCell, files: dict[str, Any]) -> None:
    r = app.client.post("/calibrations", json=files["npoint"], headers=app.auth(),
                        params={"kind": "npoint", "camera_id": "cam0", "robot_id": "robot0"})
    assert r.status_code == 201, r.text
    r = app.client.post("/calibrations", json=files["npoint"], headers=app.auth(), params={"kind": "camera"})
    assert r.status_code == 422
    err = r.json()["error"]
    assert err["code"] == "not_a_calibration" and "is a npoint calibration" in err["message"]
    r = app.client.post("/calibrations", json=files["npoint"], headers=app.auth(), params={"robot_id": "arm9"})
    assert r.status_code == 422 and r.json()["error"]["code"] == "unknown_device"
    assert "robot0" in r.json()["error"]["message"]
    r = app.client.post("/calibrations", json=files["camera"], headers=app.auth(), params={"robot_id": "robot0"})
    assert r.status_code == 422 and "camera alone" in r.json()["error"]["message"]


@pytest.mark.parametrize("mutate,words", [
    (lambda d: d.update(K=[[1400, 0, 640], [0, 1400, 512]]), "3x3"),
    (lambda d: d.update(width=-5), "width"),
    (lambda d: d.update(width=10**9), "width"),
    (lambda d: d.update(dist=[0.1]), "distortion coefficients"),
    (lambda d: d.update(K=[[1400, 0, 9000], [0, 1400, 512], [0, 0, 1]]), "principal point"),
    (lambda d: d.update(verdict="fine"), "verdict"),
])
def test_a_camera_file_with_a_wrong_value_is_422_naming_it(app: AppCell, files: dict[str, Any], mutate: Any,
                                                          words: str) -> None:
    bad = json.loads(json.dumps(files["camera"]))
    mutate(bad)
    r = app.client.post("/calibrations", json=bad, headers=app.auth())
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "invalid_calibration" and words in r.json()["error"]["message"]


def test_garbage_handeye_and_npoint_are_422(app: AppCell, files: dict[str, Any]) -> None:
    he = json.loads(json.dumps(files["handeye"]))
    he["T_tool_cam"][0][0] = 7.0
    r = app.client.post("/calibrations", json=he, headers=app.auth())
    assert r.status_code == 422 and "T_tool_cam" in r.json()["error"]["message"]
    he = json.loads(json.dumps(files["handeye"]))
    del he["T_base_target"]
    r = app.client.post("/calibrations", json=he, headers=app.auth())
    assert r.status_code == 422 and "T_base_target is missing" in r.json()["error"]["message"]
    he = json.loads(json.dumps(files["handeye"]))
    he["T_tool_cam"][0][3] = 250.0  # millimetres where metres belong
    r = app.client.post("/calibrations", json=he, headers=app.auth())
    assert r.status_code == 422 and "metres" in r.json()["error"]["message"]
    npj = json.loads(json.dumps(files["npoint"]))
    npj["H"] = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]
    r = app.client.post("/calibrations", json=npj, headers=app.auth())
    assert r.status_code == 422 and "singular" in r.json()["error"]["message"]
    for body in (b"not json", b"42", b'{"hello": 1}'):
        r = app.client.post("/calibrations", content=body, headers={**app.auth(), "Content-Type": "application/json"})
        assert r.status_code == 422, body
    listed = app.client.get("/calibrations", headers=app.auth()).json()
    assert all(c["kind"] != "handeye" or c["note"].startswith("test") for c in listed)  # none of the above stored


@pytest.mark.parametrize("body,looks", [
    ({"type": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0}, "calibration target description"),
    ([{"image": "a.png", "found": True, "points": []}], "list of target detections"),
    ({"T_cam_target": np.eye(4).tolist(), "rms_px": 0.2}, "target pose"),
    ({"offset_mm": [1.0, 2.0], "rotation_centre_px": [[1, 2]], "rms_mm": 0.1}, "tool centre"),
])
def test_a_file_of_another_kind_is_named(app: AppCell, body: Any, looks: str) -> None:
    r = app.client.post("/calibrations", json=body, headers=app.auth())
    assert r.status_code == 422
    err = r.json()["error"]
    assert err["code"] == "not_a_calibration" and looks in err["message"]
    assert "cam.json" in err["message"] and "he.json" in err["message"]  # what to give instead


def test_an_operator_may_not_add(tmp_path: Path, files: dict[str, Any]) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(run_cli("config", "default").stdout)
    op = json.loads(run_cli("token", "add", "--config", str(cfg), "--name", "op", "--role", "operator").stdout)["token"]
    eng = json.loads(run_cli("token", "add", "--config", str(cfg), "--name", "eng", "--role", "engineer").stdout)
    with in_process_cell(tmp_path, cfg, token=eng["token"]) as a:
        r2 = a.client.post("/calibrations", json=files["camera"], headers=a.auth(op))
        assert r2.status_code == 403


def test_store_add_cli(tmp_path: Path, files: dict[str, Any]) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(run_cli("config", "default").stdout.replace("path: null", f"path: {tmp_path / 'store.db'}"))
    for name in ("camera", "handeye4"):
        (tmp_path / f"{name}.json").write_text(json.dumps(files[name]))
    r = run_cli("store", "add", str(tmp_path / "camera.json"), "--config", str(cfg), "--note", "bench camera")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["kind"] == "camera" and out["version"] == 1 and out["activated"] is False
    assert out["note"] == "bench camera" and out["creator"].startswith("cli:")
    r = run_cli("store", "add", str(tmp_path / "handeye4.json"), "--config", str(cfg), "--robot", "robot0")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["kind"] == "handeye" and json.loads(r.stdout)["robot_id"] == "robot0"
    (tmp_path / "bad.json").write_text('{"model": "opencv5", "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "dist": [0]}')
    r = run_cli("store", "add", str(tmp_path / "bad.json"), "--config", str(cfg))
    assert r.returncode == 2 and r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1 and "bad.json" in r.stderr and "width" in r.stderr
    (tmp_path / "dets.json").write_text(json.dumps([{"image": "a.png", "found": False, "points": []}]))
    r = run_cli("store", "add", str(tmp_path / "dets.json"), "--config", str(cfg))
    assert r.returncode == 2 and "detections" in r.stderr and "cam.json" in r.stderr
    (tmp_path / "nan.json").write_text(json.dumps(files["camera"]).replace("0.12", "NaN"))
    r = run_cli("store", "add", str(tmp_path / "nan.json"), "--config", str(cfg))
    assert r.returncode == 2 and "rms_px is not a finite number" in r.stderr
    r = run_cli("store", "add", str(tmp_path / "missing.json"), "--config", str(cfg))
    assert r.returncode == 2 and "missing.json" in r.stderr and "Traceback" not in r.stderr


def test_random_garbage_in_a_calibration_file_is_always_a_typed_refusal() -> None:
    """Values of every JSON type put into good files: a CalibrationFileError (422) or acceptance, never
    another exception (which the service would answer as a 500)."""
    import contextlib
    import random

    from cellctl.calibration_file import CalibrationFileError, check_calibration

    rng = random.Random(7)
    keys = ["K", "model", "width", "height", "dist", "H", "setup", "T_tool_cam", "T_base_target", "camera",
            "verdict", "dof", "covariance", "rms_mm", "loo_rms_mm", "notes", "affine", "reflection"]

    def value(depth: int = 0) -> Any:
        kind = rng.randrange(7 if depth < 3 else 5)
        if kind == 0:
            return rng.choice([0, 1, -1, 1e308, 3, 10**30, True, None])
        if kind == 1:
            return rng.choice(["", "opencv5", "eye-in-hand", "affine", "x"])
        if kind == 2:
            return [[rng.random() for _ in range(rng.choice([3, 4]))] for _ in range(rng.choice([3, 4]))]
        if kind in (3, 4):
            return rng.random() * 1e3
        if kind == 5:
            return [value(depth + 1) for _ in range(rng.randrange(4))]
        return {rng.choice(keys): value(depth + 1) for _ in range(rng.randrange(6))}

    eye = np.eye(4).tolist()
    good = [{**CAM.to_dict()}, {"setup": "eye-in-hand", "T_tool_cam": eye, "T_base_target": eye},
            {"model": "affine", "H": np.eye(3).tolist()}]
    for _ in range(3000):
        data: Any = json.loads(json.dumps(rng.choice(good)))
        for _ in range(rng.randrange(1, 3)):
            data[rng.choice(keys)] = value()
        if rng.random() < 0.1:
            data = value()
        with contextlib.suppress(CalibrationFileError):
            check_calibration(data, rng.choice([None, "camera", "handeye", "npoint"]))
