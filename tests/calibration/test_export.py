"""Exports and imports round-trip; impossible exports are refused clearly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration import io as cal_io
from calibration.camera_model import CameraModel
from calibration.io import CameraFileError, camera_from_json, read_camera, read_pose, write_camera

K = np.array([[1100.5, 0.0, 645.25], [0.0, 1098.125, 478.75], [0.0, 0.0, 1.0]])
CAMS = {
    "opencv5": CameraModel("opencv5", 1280, 960, K, np.array([-0.25, 0.08, 0.001, -0.0005, -0.01])),
    "opencv8": CameraModel("opencv8", 1280, 960, K, np.array([0.1, -0.05, 0.001, 0.0005, 0.002, 0.3, -0.02, 0.01])),
    "division": CameraModel("division", 1280, 960, K, np.array([-0.2])),
}


def _same(a: CameraModel, b: CameraModel) -> None:
    assert a.model == b.model and a.size == b.size
    assert np.allclose(a.K, b.K, rtol=1e-12) and np.allclose(a.dist, b.dist, rtol=1e-12)


@pytest.mark.parametrize("model", ["opencv5", "opencv8"])
def test_opencv_yaml_round_trip(tmp_path: Path, model: str) -> None:
    f = tmp_path / "cam.yaml"
    cal_io.write_opencv_yaml(CAMS[model], f)
    assert "camera_matrix" in f.read_text()
    _same(cal_io.read_opencv_yaml(f), CAMS[model])


@pytest.mark.parametrize("model", ["opencv5", "opencv8"])
def test_ros_round_trip(tmp_path: Path, model: str) -> None:
    f = tmp_path / "ci.yaml"
    cal_io.write_ros_yaml(CAMS[model], f, "cam0")
    text = f.read_text()
    assert "camera_name: cam0" in text and ("plumb_bob" in text) == (model == "opencv5")
    _same(cal_io.read_ros_yaml(f), CAMS[model])


def test_halcon_round_trip() -> None:
    text = cal_io.halcon_cam_par(CAMS["division"], 3.45e-6)
    assert "area_scan_division" in text and "Kappa:kappa:" in text
    _same(cal_io.read_halcon_cam_par(text), CAMS["division"])


def test_refusals(tmp_path: Path) -> None:
    with pytest.raises(cal_io.ExportError, match="division"):
        cal_io.write_opencv_yaml(CAMS["division"], tmp_path / "x.yaml")
    with pytest.raises(cal_io.ExportError, match="division"):
        cal_io.ros_camera_info(CAMS["division"])
    with pytest.raises(cal_io.ExportError, match="division model"):
        cal_io.halcon_cam_par(CAMS["opencv5"], 3e-6)
    with pytest.raises(cal_io.ExportError, match="no such file"):
        cal_io.read_opencv_yaml(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nimage_width: 10\n")
    with pytest.raises(cal_io.ExportError, match="camera_matrix"):
        cal_io.read_opencv_yaml(bad)
    with pytest.raises(cal_io.ExportError, match="lack"):
        cal_io.read_halcon_cam_par("Focus:foc: 0.01;")


def test_opencv_yaml_with_four_coefficients(tmp_path: Path) -> None:
    import cv2

    f = tmp_path / "four.yml"
    fs = cv2.FileStorage(str(f), cv2.FILE_STORAGE_WRITE)
    fs.write("cameraMatrix", K)
    fs.write("distCoeffs", np.array([[0.1, 0.01, 0.0, 0.0]]))
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.release()
    cam = cal_io.read_opencv_yaml(f)
    assert cam.model == "opencv5" and cam.dist[4] == 0.0


def test_cam_json_round_trip_and_errors(tmp_path: Path) -> None:
    f = tmp_path / "cam.json"
    write_camera(f, {**CAMS["division"].to_dict(), "rms_px": 0.1, "extra": np.float64(2.0)})
    cam, data = read_camera(f)
    _same(cam, CAMS["division"])
    assert data["extra"] == 2.0
    f.write_text("{not json")
    with pytest.raises(CameraFileError, match="not valid JSON"):
        read_camera(f)
    with pytest.raises(CameraFileError, match="cannot read"):
        read_camera(tmp_path / "none.json")
    with pytest.raises(CameraFileError, match="lacks"):
        camera_from_json({"model": "opencv5", "width": 10})
    with pytest.raises(CameraFileError, match="3x3"):
        camera_from_json({"model": "opencv5", "width": 10, "height": 10, "K": [1, 2], "dist": [0] * 5})
    with pytest.raises(CameraFileError, match="distortion coefficients"):
        camera_from_json({**CAMS["opencv5"].to_dict(), "dist": [0.1]})
    p = tmp_path / "pose.json"
    p.write_text('{"T_cam_target": [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]}')
    assert read_pose(p)[2, 3] == 0.5
    p.write_text('{"rms_px": 1}')
    with pytest.raises(CameraFileError, match="lacks 'T_cam_target'"):
        read_pose(p)
    p.write_text('{"T_cam_target": [[2,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]}')
    with pytest.raises(CameraFileError, match="rotation"):
        read_pose(p)
