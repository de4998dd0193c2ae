"""``cellctl calib handeye``: hand-eye calibration from a folder of images and its ``poses.csv``.

Reads ``DIR/poses.csv`` (shared/INTERFACES.md §3: ``image,x,y,z,rx,ry,rz``, UR TCP-pose form),
detects the target in each listed image, and prints ``he.json`` (shared/INTERFACES.md §4):
``T_tool_cam`` + ``T_base_target`` (eye-in-hand) or ``T_base_cam`` + ``T_tool_target``
(eye-to-hand), residuals, the 1-σ uncertainty and leave-one-out prediction. Warnings (views left
out, pairs dropped, mis-paired images) go to stderr; a convention mistake or degenerate motion
stops it with one clear line.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError

log = logging.getLogger("cellctl.calib.handeye")


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "handeye", help="hand-eye calibration (eye-in-hand or eye-to-hand)",
        description="Hand-eye calibration from DIR/poses.csv (image,x,y,z,rx,ry,rz: T_base_tool in UR's "
                    "TCP-pose form, metres + rotation vector) and the images it lists.")
    p.add_argument("--setup", required=True, choices=["eye-in-hand", "eye-to-hand"])
    p.add_argument("--camera", required=True, help="camera calibration cam.json")
    p.add_argument("--target", required=True, help="target description YAML")
    p.add_argument("--dataset", required=True, metavar="DIR", help="folder with poses.csv and the images")
    p.add_argument("--detections", help="use detections JSON (output of cellctl detect) instead of detecting")
    p.add_argument("--robot-sigma-mm", type=float, default=0.05,
                   help="robot position noise, 1-sigma per axis, mm (default 0.05, UR-class)")
    p.add_argument("--robot-sigma-deg", type=float, default=0.01,
                   help="robot orientation noise, 1-sigma per axis, deg (default 0.01)")
    p.add_argument("--estimate-robot-noise", action="store_true",
                   help="estimate the robot's noise from the data (real robots: absolute error is often mm)")
    p.add_argument("--no-loo", action="store_true", help="skip the leave-one-out validation (faster)")
    p.add_argument("--out", dest="out_json", help="write he.json here too")
    p.set_defaults(func=run)


def _camera(path: str) -> Any:
    try:
        from calibration.camera_io import read_camera
    except ImportError:  # pragma: no cover - camera_io ships with the package
        from calibration.camera_model import CameraModel

        try:
            return CameraModel.from_dict(json.loads(Path(path).read_text()))
        except OSError as exc:
            raise CommandError(f"{path}: cannot read camera file ({exc.strerror})") from exc
        except json.JSONDecodeError as exc:
            raise CommandError(f"{path}: not valid JSON ({exc.msg})") from exc
    return read_camera(path)[0]


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.handeye import RobotNoise, calibrate_handeye
    from calibration.observations import Detection
    from calibration.robot_poses import read_poses_csv
    from calibration.targets import load_target

    target = load_target(args.target)
    camera = _camera(args.camera)
    folder = Path(args.dataset)
    if not folder.is_dir():
        raise CommandError(f"{folder}: no such dataset folder (it must hold poses.csv and the images)")
    poses = read_poses_csv(folder / "poses.csv")
    if args.detections:
        try:
            data = json.loads(Path(args.detections).read_text())
            by_name = {d["image"]: Detection.from_json(d) for d in data}
        except OSError as exc:
            raise CommandError(f"{args.detections}: cannot read detections ({exc.strerror})") from exc
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise CommandError(f"{args.detections}: not a cellctl detect JSON list ({exc})") from exc
        missing = [n for n in poses.images if n not in by_name and Path(n).name not in by_name]
        if missing:
            raise CommandError(f"{args.detections}: no detection for {missing[:3]} listed in poses.csv")
        detections = [by_name.get(n) or by_name[Path(n).name] for n in poses.images]
    else:
        missing = [n for n in poses.images if not (folder / n).is_file()]
        if missing:
            raise CommandError(f"{folder}: poses.csv lists images that are not there: {missing[:3]}")
        from calibration.detect import detect_file

        detections = []
        for k, name in enumerate(poses.images):
            log.info("detecting %s (%d/%d)", name, k + 1, len(poses.images))
            det = detect_file(folder / name, target)
            det.image = name
            detections.append(det)
    try:
        noise = RobotNoise(args.robot_sigma_mm, args.robot_sigma_deg)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    result = calibrate_handeye(args.setup, poses.T_base_tool, detections, camera, target, noise,
                               raw_ur_poses=poses.ur_poses, leave_one_out=not args.no_loo,
                               estimate_robot_noise=args.estimate_robot_noise)
    out = result.to_json()
    for prob in out["verdict"]["problems"]:
        print(f"cellctl: {prob['severity']}: {prob['message']}", file=sys.stderr)
    return out
