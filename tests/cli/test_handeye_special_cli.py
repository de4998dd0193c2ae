"""The command line beyond 6-DOF AX=XB: ``calib handeye --dof 4``, ``--T-base-target`` /
``--T-tool-target`` (``--check``), ``calib tcp``, ``pose --points --method``; bad input; and the
commands of docs/calibrations-beyond-6dof.md, run as written."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.camera_model import CameraModel
from calibration.geometry import invert, look_at, transform_error, transform_to_ur_pose
from calibration.handeye import HandEyeError, RobotNoise, calibrate_handeye
from calibration.io import write_poses_csv
from calibration.synthetic import perturb_pose, simulate_handeye, simulate_scara, write_example
from calibration.targets import Chessboard
from cellctl.cli import main

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "calibrations-beyond-6dof.md"


def _he(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, dict | None, str]:
    code = main(["calib", "handeye", *args])
    cap = capsys.readouterr()
    return code, (json.loads(cap.out) if code == 0 else None), cap.err


def _scara_args(d: dict[str, str]) -> list[str]:
    folder = str(Path(d["poses.csv"]).parent)
    return ["--setup", "eye-in-hand", "--camera", d["cam.json"], "--target", d["board.yaml"], "--dataset", folder,
            "--detections", d["detections.json"]]


def test_dof4_command_recovers_the_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = write_example("scara", str(tmp_path / "scara"), seed=3)
    truth = json.loads(Path(d["truth.json"]).read_text())
    out_file = tmp_path / "he4.json"
    code, he, err = _he([*_scara_args(d), "--dof", "4", "--target-z-mm", str(truth["target_z_mm"]),
                         "--out", str(out_file)], capsys)
    assert code == 0, err
    assert he is not None and he["dof"] == 4 and json.loads(out_file.read_text()) == he
    assert "tool z axis" in he["fixed_by_constraint"]["fixed"][0]
    assert len(he["leave_one_out"]["per_pose"]) == 14 and he["leave_one_out"]["rms_px"]["rms"] < 1.0
    rot, trans = transform_error(he["T_tool_cam"], truth["T_tool_cam"])
    assert np.degrees(rot) <= 3 * he["uncertainty"]["rot_deg"] and trans * 1e3 <= 3 * he["uncertainty"]["trans_mm"]
    # cellctl map takes the 4-DOF result as it takes a 6-DOF one
    pose = ",".join(repr(float(v)) for v in np.genfromtxt(d["poses.csv"], delimiter=",", skip_header=1)[0, 1:])
    assert main(["map", "--calib", str(out_file), "--plane-z-mm", "12", "--robot-pose", pose, "960", "600"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["z_mm"] == pytest.approx(12.0) and 0 < m["sigma"]["total_mm"] < 1.0


def test_dof4_options_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = write_example("scara", str(tmp_path / "scara"))
    code, _, err = _he([*_scara_args(d), "--dof", "4"], capsys)
    assert code == 2 and "--dof 4 needs --target-z-mm" in err
    code, _, err = _he([*_scara_args(d), "--target-z-mm", "12"], capsys)
    assert code == 2 and "--target-z-mm belongs to --dof 4" in err
    code, _, err = _he([*_scara_args(d), "--dof", "4", "--target-z-mm", "12", "--pixel-sigma-px", "-1"], capsys)
    assert code == 2 and "--pixel-sigma-px must be a positive number" in err


def test_6dof_solver_refuses_4dof_data_pointing_to_dof4(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = write_example("scara", str(tmp_path / "scara"))
    code, _, err = _he(_scara_args(d), capsys)
    assert code == 2 and "--dof 4" in err and err.count("\n") == 1
    # the library's 6-DOF solver itself points there too (a field the front ends word)
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                      np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
    s = simulate_scara("eye-to-hand", 10, np.random.default_rng(1), camera=cam, target=Chessboard(7, 5, 25.0))
    with pytest.raises(HandEyeError, match="one axis") as refused:
        calibrate_handeye("eye-to-hand", s.G_recorded, s.detections, cam, s.target, RobotNoise(0.02, 0.01))
    assert refused.value.alternative == "dof4"


@pytest.fixture(scope="module")
def measured_set(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, np.ndarray]:
    d = tmp_path_factory.mktemp("measured")
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958], [0, 1900, 603], [0, 0, 1]]),
                      np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
    board = Chessboard(8, 6, 25.0)
    noise = RobotNoise(0.03, 0.005)
    rng = np.random.default_rng(21)
    s = simulate_handeye("eye-in-hand", 10, rng, camera=cam, target=board, robot_noise=noise)
    Z_meas = perturb_pose(s.Z_true, rng, noise)
    write_poses_csv(d / "poses.csv", [x.image for x in s.detections[:3]],
                    np.array([transform_to_ur_pose(g) for g in s.G_recorded[:3]]))
    (d / "dets.json").write_text(json.dumps([x.to_json() for x in s.detections[:3]]))
    (d / "cam.json").write_text(json.dumps(cam.to_dict()))
    (d / "board.yaml").write_text("type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 25.0\n")
    (d / "frame.json").write_text(json.dumps({"T_base_target": Z_meas.tolist()}))
    he = calibrate_handeye("eye-in-hand", s.G_recorded, s.detections, cam, board, noise, leave_one_out=False)
    (d / "he.json").write_text(json.dumps(he.to_json()))
    return d, s, Z_meas


def test_measured_frame_command(measured_set: tuple[Path, object, np.ndarray],
                                capsys: pytest.CaptureFixture[str]) -> None:
    d, s, _ = measured_set
    base = ["--setup", "eye-in-hand", "--camera", str(d / "cam.json"), "--target", str(d / "board.yaml"),
            "--dataset", str(d), "--detections", str(d / "dets.json"), "--robot-sigma-mm", "0.03",
            "--robot-sigma-deg", "0.005"]
    code, out, err = _he([*base, "--T-base-target", str(d / "frame.json"), "--check", str(d / "he.json")], capsys)
    assert code == 0, err
    assert out is not None and out["method"] == "measured_frame" and out["stations"] == 3
    rot, trans = transform_error(out["T_tool_cam"], s.X_true)  # type: ignore[attr-defined]
    assert np.degrees(rot) <= 0.03 and trans * 1e3 <= 0.2
    assert out["check"]["trans_sigmas"] < 4.0 and out["check"]["trans_mm"] < 0.3
    code, _, err = _he([*base, "--T-tool-target", str(d / "frame.json")], capsys)
    assert code == 2 and "takes the measured frame as --T-base-target" in err
    mm = d / "frame_mm.json"
    T = np.array(json.loads((d / "frame.json").read_text())["T_base_target"])
    T[:3, 3] *= 1000.0
    mm.write_text(json.dumps({"T_base_target": T.tolist()}))
    code, _, err = _he([*base, "--T-base-target", str(mm)], capsys)
    assert code == 2 and "must be in metres" in err
    code, _, err = _he([*base, "--check", str(d / "he.json")], capsys)
    assert code == 2 and "--check he.json compares against a measured-frame solution" in err


def test_tcp_command_and_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = write_example("tcp", str(tmp_path / "tcp"))
    npj = tmp_path / "np.json"
    assert main(["calib", "npoint", "--pairs", d["pairs.csv"], "--camera", d["cam.json"], "--out", str(npj)]) == 0
    capsys.readouterr()
    assert main(["calib", "tcp", "--npoint", str(npj), "--rotations", d["rot.csv"]]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.linalg.norm(np.array(out["offset_mm"]) - [32.5, -18.0]) <= 0.05
    assert len(out["rotation_centre_px"]) == 2 and out["uncertainty"]["offset_mm"] > 0 and out["rms_mm"] < 0.05
    lines = Path(d["rot.csv"]).read_text().splitlines()
    two = tmp_path / "two.csv"
    two.write_text("\n".join([lines[0], lines[1], lines[2]]) + "\n")
    assert main(["calib", "tcp", "--npoint", str(npj), "--rotations", str(two)]) == 2
    assert "only 2 angle(s); a circle needs at least 3" in capsys.readouterr().err
    short = tmp_path / "short.csv"
    rows = [ln.split(",") for ln in lines[1:4]]
    rows = [[*r[:4], f"{10.0 + 5.0 * k:.1f}"] for k, r in enumerate(rows)]
    short.write_text("\n".join([lines[0], *(",".join(r) for r in rows)]) + "\n")
    assert main(["calib", "tcp", "--npoint", str(npj), "--rotations", str(short)]) == 2
    assert "span only 10.0 deg" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("u,v\n1,2\n")
    assert main(["calib", "tcp", "--npoint", str(npj), "--rotations", str(bad)]) == 2
    assert "needs the header u_px,v_px,x_mm,y_mm,rz_deg" in capsys.readouterr().err


def test_pose_from_points_by_method(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cam = CameraModel("opencv5", 1280, 960, np.array([[1100.0, 0, 640], [0, 1100, 480], [0, 0, 1]]),
                      np.array([-0.1, 0.02, 0.0, 0.0, 0.0]))
    board = Chessboard(8, 6, 25.0)
    (tmp_path / "cam.json").write_text(json.dumps(cam.to_dict()))
    (tmp_path / "board.yaml").write_text("type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 25.0\n")
    T = invert(look_at([0.05, -0.02, -0.9], [0.09, 0.06, 0.0], up=[0, -1, 0]))
    tp = board.points()
    uv = cam.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3]) + np.random.default_rng(0).normal(0, 0.2, (len(tp.ids), 2))
    obs = tmp_path / "obs.csv"
    obs.write_text("id,u_px,v_px\n" + "".join(f"{i},{u},{v}\n" for i, (u, v) in zip(tp.ids, uv, strict=True)))
    base = ["pose", "--camera", str(tmp_path / "cam.json"), "--target", str(tmp_path / "board.yaml")]
    results = {}
    for method in ("rpnp", "sqpnp", "ippe", "epnp", "auto"):
        assert main([*base, "--points", str(obs), "--method", method]) == 0
        results[method] = json.loads(capsys.readouterr().out)
        assert results[method]["requested_method"] == method
        _, trans = transform_error(results[method]["T_cam_target"], T)
        assert trans * 1e3 < 3 * results[method]["uncertainty"]["trans_mm"]
    assert results["rpnp"]["method"] == "rpnp"
    assert np.allclose(results["rpnp"]["T_cam_target"], results["sqpnp"]["T_cam_target"], atol=1e-7)
    three = tmp_path / "three.csv"
    three.write_text("id,u_px,v_px\n" + "".join(f"{i},{u},{v}\n" for i, (u, v) in zip(tp.ids[:3], uv[:3],
                                                                                       strict=True)))
    assert main([*base, "--points", str(three), "--method", "rpnp"]) == 2
    assert "at least 4 points" in capsys.readouterr().err
    assert main([*base, "--points", str(obs), "image.png"]) == 2
    assert "either IMAGE or --points" in capsys.readouterr().err


def test_doc_commands_run_as_written(tmp_path: Path) -> None:
    """Every bash block of the doc runs (with /tmp/ pointed at a fresh folder) and ends well."""
    text = DOC.read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 2
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for block in blocks:
        script = "set -euo pipefail\n" + block.replace("/tmp/", f"{tmp_path}/")
        run = subprocess.run(["bash", "-c", script], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
    he4 = json.loads((tmp_path / "scara" / "he4.json").read_text())
    assert he4["dof"] == 4 and he4["verdict"]["ok"]
    tcp = json.loads((tmp_path / "tcp" / "tcp.json").read_text())
    assert np.linalg.norm(np.array(tcp["offset_mm"]) - [32.5, -18.0]) <= 0.05
