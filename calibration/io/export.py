"""Camera exports: OpenCV FileStorage YAML, ROS ``camera_info`` YAML, HALCON camera parameters.

- OpenCV: the keys of OpenCV's calibration sample (``camera_matrix``, ``distortion_coefficients``,
  ``image_width``, ``image_height``), written and read with ``cv2.FileStorage``. Import accepts
  4, 5 or 8 coefficients (4 is read as k3 = 0). The division model has no OpenCV form and is
  refused.
- ROS: ``sensor_msgs/CameraInfo`` YAML as ``camera_calibration_parsers`` writes it
  (``plumb_bob`` for opencv5, ``rational_polynomial`` for opencv8).
- HALCON: the ``area_scan_division`` parameter file as ``write_cam_par`` lays it out (Focus in m,
  Kappa in 1/m^2, Sx/Sy in m, Cx/Cy in px, image size). Only the division model: HALCON's
  polynomial model is a different function (it maps distorted to undistorted points).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from calibration import CalibrationError
from calibration.camera_model import CameraModel


class ExportError(CalibrationError):
    """A model cannot be expressed in the requested format, or an import file is malformed."""


def _opencv_only(camera: CameraModel, fmt: str) -> None:
    if camera.model == "fisheye4":
        raise ExportError(f"{fmt} (a pinhole camera matrix with OpenCV's plumb-bob or rational distortion) "
                          "cannot express the fisheye4 (Kannala-Brandt) model; use the cam.json with cellctl, or "
                          "calibrate with the opencv5 or opencv8 lens model")
    if camera.model == "splined":
        raise ExportError(f"{fmt} (a pinhole camera matrix with OpenCV's plumb-bob or rational distortion) "
                          "cannot express the splined stereographic model (a B-spline correction over the "
                          "stereographic plane); use the cam.json with cellctl, or calibrate with the opencv5 "
                          "or opencv8 lens model")
    if camera.model == "division":
        raise ExportError(f"{fmt} cannot express the division model; export it for HALCON, or calibrate "
                          "the camera with the opencv5 or opencv8 lens model")


def write_opencv_yaml(camera: CameraModel, path: str | Path) -> None:
    _opencv_only(camera, "OpenCV YAML")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ExportError(f"{path}: cannot open for writing")
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_matrix", camera.K)
        fs.write("distortion_coefficients", camera.dist.reshape(1, -1))
        fs.write("distortion_model", "plumb_bob" if camera.model == "opencv5" else "rational_polynomial")
    finally:
        fs.release()


def read_opencv_yaml(path: str | Path) -> CameraModel:
    """A camera from an OpenCV FileStorage YAML/XML file (calibration sample key names, or
    ``cameraMatrix``/``distCoeffs``)."""
    p = Path(path)
    if not p.is_file():
        raise ExportError(f"{p}: no such file")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ExportError(f"{p}: not an OpenCV FileStorage file ({exc.err})") from exc
    if not fs.isOpened():
        raise ExportError(f"{p}: not an OpenCV FileStorage file")
    try:
        def mat(*names: str) -> np.ndarray | None:
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return np.asarray(node.mat(), dtype=np.float64)
            return None

        def num(*names: str) -> int | None:
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return int(node.real())
            return None

        K = mat("camera_matrix", "cameraMatrix", "K")
        d = mat("distortion_coefficients", "distCoeffs", "dist_coeffs", "D")
        w = num("image_width", "imageWidth", "width")
        h = num("image_height", "imageHeight", "height")
    finally:
        fs.release()
    if K is None or K.shape != (3, 3):
        raise ExportError(f"{p}: no 3x3 camera_matrix")
    if d is None:
        raise ExportError(f"{p}: no distortion_coefficients")
    if w is None or h is None:
        raise ExportError(f"{p}: no image_width/image_height")
    d = d.reshape(-1)
    if d.size == 4:
        d = np.concatenate([d, [0.0]])
    if d.size == 5:
        model = "opencv5"
    elif d.size == 8:
        model = "opencv8"
    else:
        raise ExportError(f"{p}: {d.size} distortion coefficients; cellctl reads 4, 5 or 8")
    return CameraModel(model, w, h, K, d)  # type: ignore[arg-type]


def ros_camera_info(camera: CameraModel, name: str = "camera") -> dict[str, Any]:
    _opencv_only(camera, "ROS camera_info")
    P = np.zeros((3, 4))
    P[:, :3] = camera.K
    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": camera.K.reshape(-1).tolist()},
        "distortion_model": "plumb_bob" if camera.model == "opencv5" else "rational_polynomial",
        "distortion_coefficients": {"rows": 1, "cols": int(camera.dist.size), "data": camera.dist.tolist()},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).reshape(-1).tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": P.reshape(-1).tolist()},
    }


def write_ros_yaml(camera: CameraModel, path: str | Path, name: str = "camera") -> None:
    Path(path).write_text(yaml.safe_dump(ros_camera_info(camera, name), sort_keys=False))


def read_ros_yaml(path: str | Path) -> CameraModel:
    p = Path(path)
    try:
        d = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ExportError(f"{p}: cannot read ROS camera_info YAML ({exc})") from exc
    try:
        K = np.asarray(d["camera_matrix"]["data"], dtype=np.float64).reshape(3, 3)
        dist = np.asarray(d["distortion_coefficients"]["data"], dtype=np.float64)
        model = {"plumb_bob": "opencv5", "rational_polynomial": "opencv8"}[d["distortion_model"]]
        return CameraModel(model, int(d["image_width"]), int(d["image_height"]), K, dist)  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError) as exc:
        raise ExportError(f"{p}: not a camera_info YAML with a plumb_bob or rational_polynomial model ({exc})"
                          ) from exc


_HALCON_FIELDS = [
    ("Focus", "foc", "DOUBLE:0.0:", "Focal length of the lens"),
    ("Kappa", "kappa", "DOUBLE::", "Radial distortion coefficient"),
    ("Sx", "sx", "DOUBLE:0.0:", "Width of a cell on the sensor"),
    ("Sy", "sy", "DOUBLE:0.0:", "Height of a cell on the sensor"),
    ("Cx", "cx", "DOUBLE::", "X-coordinate of the image center"),
    ("Cy", "cy", "DOUBLE::", "Y-coordinate of the image center"),
    ("ImageWidth", "imgw", "INT:1:32767", "Width of the images"),
    ("ImageHeight", "imgh", "INT:1:32767", "Height of the images"),
]


def halcon_cam_par(camera: CameraModel, pixel_pitch_m: float) -> str:
    """HALCON camera parameter file text (``area_scan_division``) of a division-model camera."""
    if camera.model != "division":
        raise ExportError("HALCON export supports the division model (area_scan_division); calibrate the "
                          "camera with the division lens model")
    if not pixel_pitch_m > 0:
        raise ExportError("HALCON needs the sensor cell width (pixel pitch) in metres, > 0")
    p = camera.to_halcon(pixel_pitch_m)
    lines = ["ParGroup: Camera: Parameter;", '\t"Internal camera parameters";', "",
             "Camera:CameraType:\t'area_scan_division';", ""]
    for name, short, typ, doc in _HALCON_FIELDS:
        v = p[name]
        val = f"{int(round(v))}" if typ.startswith("INT") else f"{v:.12g}"
        lines += [f"{name}:{short}:\t{val};", f"\t{typ};", f'\t"{doc}";', ""]
    tup = ", ".join([f"{p[n]:.12g}" for n, *_ in _HALCON_FIELDS])
    lines.append(f"* HDevelop tuple: ['area_scan_division', {tup}]")
    return "\n".join(lines) + "\n"


def read_halcon_cam_par(text: str) -> CameraModel:
    vals: dict[str, float] = {}
    for m in re.finditer(r"^(\w+):\w+:\s*([-+0-9.eE]+);", text, flags=re.MULTILINE):
        vals[m.group(1)] = float(m.group(2))
    missing = [n for n, *_ in _HALCON_FIELDS if n not in vals]
    if missing:
        raise ExportError(f"HALCON camera parameters lack {missing}")
    if "area_scan_division" not in text and "CameraType" in text:
        raise ExportError("only HALCON's area_scan_division camera type is supported")
    return CameraModel.from_halcon(vals)
