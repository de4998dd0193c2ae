"""``cellctl calib export`` / ``cellctl calib import``: camera files for OpenCV, ROS and HALCON."""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "export", help="write cam.json as OpenCV YAML, ROS camera_info YAML or HALCON camera parameters")
    p.add_argument("--camera", required=True, help="camera JSON (cam.json)")
    p.add_argument("--format", required=True, choices=["opencv", "ros", "halcon"])
    p.add_argument("--out", dest="out_file", required=True, help="file to write")
    p.add_argument("--pixel-pitch-um", type=float, help="sensor cell width in micrometres (HALCON)")
    p.add_argument("--name", default="camera", help="camera_name (ROS)")
    p.set_defaults(func=run_export)
    q: argparse.ArgumentParser = sub.add_parser(
        "import", help="read a camera file of OpenCV, ROS or HALCON into cam.json",
        description="Read a camera calibration made elsewhere into cam.json. --format opencv (default): an "
                    "OpenCV FileStorage YAML/XML with camera_matrix and distortion_coefficients; ros: a ROS "
                    "camera_info YAML; halcon: HALCON camera parameters as write_cam_par writes them "
                    "(area_scan_division only).")
    q.add_argument("file", help="the camera file (see --format)")
    q.add_argument("--format", default="opencv", choices=["opencv", "ros", "halcon"],
                   help="opencv: FileStorage YAML/XML (default); ros: camera_info YAML; "
                        "halcon: write_cam_par text (area_scan_division)")
    q.add_argument("--out", dest="out_json", help="write cam.json here too")
    q.set_defaults(func=run_import)


def run_export(args: argparse.Namespace) -> dict[str, Any]:
    from calibration import io as cal_io
    from calibration.io import read_camera

    camera, _ = read_camera(args.camera)
    if args.format == "opencv":
        cal_io.write_opencv_yaml(camera, args.out_file)
    elif args.format == "ros":
        cal_io.write_ros_yaml(camera, args.out_file, args.name)
    else:
        if not args.pixel_pitch_um:
            raise CommandError("HALCON export needs --pixel-pitch-um (the sensor cell width, e.g. 3.45)")
        Path(args.out_file).write_text(cal_io.halcon_cam_par(camera, args.pixel_pitch_um * 1e-6))
    return {"written": str(args.out_file), "format": args.format, "model": camera.model}


def run_import(args: argparse.Namespace) -> dict[str, Any]:
    from calibration import io as cal_io

    if args.format == "opencv":
        import cv2

        try:
            camera = cal_io.read_opencv_yaml(args.file)
        except (cv2.error, SystemError) as exc:
            # OpenCV's parser fails on anything that is not FileStorage YAML/XML (a SystemError from its binding).
            cause = getattr(exc, "__cause__", None) or exc
            detail = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
            detail = re.sub(r"^OpenCV\(.*?\) \S+: error: \(-?\d+:[^)]*\) ", "", detail)
            raise CommandError(f"{args.file}: OpenCV cannot parse it as a FileStorage YAML/XML camera file "
                               f"({detail[:160]}); give a file written by cv2.FileStorage (or --format ros for "
                               "a ROS camera_info YAML)") from None
    elif args.format == "ros":
        camera = cal_io.read_ros_yaml(args.file)
    else:
        try:
            text = Path(args.file).read_text()
        except OSError as exc:
            raise CommandError(f"{args.file}: cannot read ({exc.strerror})") from exc
        camera = cal_io.read_halcon_cam_par(text)
    return {**camera.to_dict(), "imported_from": str(args.file)}
