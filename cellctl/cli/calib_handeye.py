"""``cellctl calib handeye``: hand-eye calibration from a folder of images and its ``poses.csv``.

Reads ``DIR/poses.csv`` (docs/datasets.md: ``image,x,y,z,rx,ry,rz``, UR TCP-pose form),
detects the target in each listed image, and prints ``he.json`` (docs/cli.md):
``T_tool_cam`` + ``T_base_target`` (eye-in-hand) or ``T_base_cam`` + ``T_tool_target``
(eye-to-hand), residuals, the 1-σ uncertainty and leave-one-out prediction. Warnings (views left
out, pairs dropped, mis-paired images) go to stderr; a convention mistake or degenerate motion
stops it with one clear line.

Beyond 6-DOF AX=XB: ``--dof 4 --target-z-mm Z`` for robots that turn the tool only about the base
z axis (``calibration.handeye.dof4``), and ``--T-base-target F.json`` / ``--T-tool-target F.json``
when the target's frame was measured by other means (``calibration.handeye.measured``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError
from cellctl.hints import CLI, handeye_message

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
    p.add_argument("--pixel-sigma-px", type=float,
                   help="image point noise, 1-sigma per coordinate, px (default: estimated from the per-view "
                        "pose residuals)")
    p.add_argument("--dof", type=int, choices=[4, 6], default=6,
                   help="6 (default): full AX=XB; 4: the tool only turns about the base z axis (SCARA, delta, "
                        "top-down picking) - needs --target-z-mm")
    p.add_argument("--target-z-mm", type=float,
                   help="--dof 4: height of the target origin in the base frame, mm (eye-to-hand: at the first "
                        "pose of poses.csv); it fixes the part of the hand-eye such motion cannot see")
    p.add_argument("--target-z-sigma-mm", type=float, default=0.1,
                   help="--dof 4: 1-sigma of --target-z-mm, mm (default 0.1)")
    p.add_argument("--T-base-target", dest="T_base_target", metavar="F.json",
                   help="eye-in-hand with a measured target frame (laser tracker): F.json holds "
                        '{"T_base_target": 4x4, metres}; works from one station')
    p.add_argument("--T-tool-target", dest="T_tool_target", metavar="F.json",
                   help='eye-to-hand with a measured target frame: F.json holds {"T_tool_target": 4x4, metres}')
    p.add_argument("--tracker-sigma-mm", type=float, default=0.03,
                   help="measured frame's position noise, 1-sigma per axis, mm (default 0.03)")
    p.add_argument("--tracker-sigma-deg", type=float, default=0.005,
                   help="measured frame's orientation noise, 1-sigma per axis, deg (default 0.005)")
    p.add_argument("--check", metavar="he.json",
                   help="with a measured frame: also report how far this AX=XB result lies from the measured-frame one")
    p.add_argument("--out", dest="out_json", help="write he.json here too")
    p.set_defaults(func=run)


def _camera(path: str) -> Any:
    try:
        from calibration.io import read_camera
    except ImportError:  # pragma: no cover - camera_io ships with the package
        from calibration.camera_model import CameraModel

        try:
            return CameraModel.from_dict(json.loads(Path(path).read_text()))
        except OSError as exc:
            raise CommandError(f"{path}: cannot read camera file ({exc.strerror})") from exc
        except json.JSONDecodeError as exc:
            raise CommandError(f"{path}: not valid JSON ({exc.msg})") from exc
    return read_camera(path)[0]


def _load(args: argparse.Namespace) -> tuple[Any, Any, Any, list[Any]]:
    """(target, camera, poses, detections) of the data set; detections in poses.csv order."""
    from calibration.io import read_poses_csv
    from calibration.observations import Detection
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
    return target, camera, poses, detections


def _camera_verdict_ok(path: str) -> bool | None:
    """The camera calibration's own verdict (cam.json), or None when the file carries none.

    An uncertain camera (verdict not ok) turns on the joint refinement of intrinsics with the hand-eye.
    """
    try:
        verdict = json.loads(Path(path).read_text()).get("verdict")
    except (OSError, ValueError, AttributeError):
        return None  # an OpenCV YAML or a file without a verdict
    ok = verdict.get("ok") if isinstance(verdict, dict) else None
    return ok if isinstance(ok, bool) else None


def _camera_covariance(path: str, camera: Any) -> Any:
    """The intrinsics covariance of cam.json (``parameters``: names + covariance) in the order the
    hand-eye uses (fx, fy, cx, cy, then the model's distortion coefficients), or None when the file
    carries none (an OpenCV YAML, a hand-written file). It enters the hand-eye uncertainty."""
    import numpy as np

    from calibration.intrinsics import param_names

    try:
        params = json.loads(Path(path).read_text()).get("parameters")
        names, cov = params["names"], np.asarray(params["covariance"], dtype=np.float64)
    except (OSError, ValueError, AttributeError, KeyError, TypeError):
        return None
    want = param_names(camera.model)
    if cov.shape != (len(names), len(names)) or not set(names) <= set(want) or not np.all(np.isfinite(cov)):
        raise CommandError(f"{path}: parameters.covariance must be a square matrix over parameters.names "
                           f"(a subset of {want}); re-run cellctl calib intrinsics or remove the parameters block")
    idx = [want.index(n) for n in names]
    full = np.zeros((len(want), len(want)))
    full[np.ix_(idx, idx)] = cov
    return full


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.handeye import HandEyeError, RobotNoise, calibrate_handeye

    if args.dof != 4 and (args.target_z_mm is not None):
        raise CommandError("--target-z-mm belongs to --dof 4 (a robot that turns only about base z); add --dof 4 "
                           "or leave it out")
    if args.dof == 4 and args.target_z_mm is None:
        raise CommandError("--dof 4 needs --target-z-mm Z: the target origin's height in the base frame (mm); "
                           "4-DOF motion cannot see it")
    measured = _measured_frame(args)
    if args.check and measured is None:
        raise CommandError("--check he.json compares against a measured-frame solution: give --T-base-target "
                           "(eye-in-hand) or --T-tool-target (eye-to-hand) too")
    if measured is not None and args.dof == 4:
        raise CommandError("--dof 4 and a measured target frame exclude each other: the measured frame alone fixes "
                           "every part of the hand-eye")
    target, camera, poses, detections = _load(args)
    try:
        noise = RobotNoise(args.robot_sigma_mm, args.robot_sigma_deg)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    if measured is not None:
        return _run_measured(args, measured, target, camera, poses, detections, noise)
    if args.dof == 4:
        from calibration.handeye import calibrate_handeye_dof4

        if not math.isfinite(args.target_z_mm):
            raise CommandError(f"--target-z-mm must be a finite height in mm (base frame), got {args.target_z_mm}")
        try:
            out = calibrate_handeye_dof4(args.setup, poses.T_base_tool, detections, camera, target, args.target_z_mm,
                                         noise, target_z_sigma_mm=args.target_z_sigma_mm,
                                         sigma_px=_pixel_sigma(args), leave_one_out=not args.no_loo).to_json()
        except HandEyeError as exc:
            raise CommandError(handeye_message(exc, CLI)) from exc
        _warn(out)
        return out
    try:
        result = calibrate_handeye(args.setup, poses.T_base_tool, detections, camera, target, noise,
                                   raw_ur_poses=poses.ur_poses, sigma_px=_pixel_sigma(args),
                                   leave_one_out=not args.no_loo,
                                   estimate_robot_noise=args.estimate_robot_noise,
                                   camera_verdict_ok=_camera_verdict_ok(args.camera),
                                   camera_covariance=_camera_covariance(args.camera, camera))
    except HandEyeError as exc:
        from calibration.handeye import is_dof4

        if is_dof4(list(poses.T_base_tool)):
            raise CommandError(f"{exc} — these poses turn the tool only about the base z axis: calibrate them "
                               "with --dof 4 --target-z-mm Z (Z: the target origin's height, base frame, mm)") from exc
        raise CommandError(handeye_message(exc, CLI)) from exc
    out = result.to_json()
    _warn(out)
    return out


def _pixel_sigma(args: argparse.Namespace) -> float | None:
    s = args.pixel_sigma_px
    if s is not None and not (s > 0 and s < 100):
        raise CommandError(f"--pixel-sigma-px must be a positive number of pixels (e.g. 0.1), got {s}")
    return None if s is None else float(s)


def _measured_frame(args: argparse.Namespace) -> Any:
    """The measured frame's 4x4 (metres) from --T-base-target / --T-tool-target, or None."""
    import numpy as np

    from calibration.geometry import PoseError, as_transform

    given = [(k, getattr(args, k)) for k in ("T_base_target", "T_tool_target") if getattr(args, k)]
    if not given:
        return None
    if len(given) > 1:
        raise CommandError("give --T-base-target (eye-in-hand) or --T-tool-target (eye-to-hand), not both")
    key, path = given[0]
    want = "T_base_target" if args.setup == "eye-in-hand" else "T_tool_target"
    if key != want:
        flag = "--T-base-target" if want == "T_base_target" else "--T-tool-target"
        raise CommandError(f"--setup {args.setup} takes the measured frame as {flag} ({want}); the other frame "
                           "belongs to the other setup")
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CommandError(f"{path}: cannot read the measured frame ({exc.strerror})") from exc
    except json.JSONDecodeError as exc:
        raise CommandError(f"{path}: not valid JSON ({exc.msg})") from exc
    if not isinstance(data, dict) or key not in data:
        raise CommandError(f'{path}: needs {{"{key}": 4x4 matrix in metres}}')
    try:
        T = as_transform(np.asarray(data[key], dtype=np.float64), key)
    except (PoseError, ValueError, TypeError) as exc:
        raise CommandError(f"{path}: {exc}") from exc
    if np.linalg.norm(T[:3, 3]) > 20.0:
        raise CommandError(f"{path}: {key} translation is {np.linalg.norm(T[:3, 3]):.0f} m away; it must be in "
                           "metres (divide millimetres by 1000)")
    return T


def _run_measured(args: argparse.Namespace, T: Any, target: Any, camera: Any, poses: Any, detections: list[Any],
                  noise: Any) -> dict[str, Any]:
    from calibration.handeye import RobotNoise, calibrate_handeye_measured, compare_handeye

    try:
        tracker = RobotNoise(args.tracker_sigma_mm, args.tracker_sigma_deg)
    except ValueError as exc:
        raise CommandError(f"tracker noise: {exc}") from exc
    res = calibrate_handeye_measured(args.setup, poses.T_base_tool, detections, camera, target, T, noise, tracker,
                                     sigma_px=_pixel_sigma(args))
    out = res.to_json()
    if args.check:
        try:
            he = json.loads(Path(args.check).read_text())
        except OSError as exc:
            raise CommandError(f"{args.check}: cannot read the hand-eye to check ({exc.strerror})") from exc
        except json.JSONDecodeError as exc:
            raise CommandError(f"{args.check}: not valid JSON ({exc.msg})") from exc
        out["check"] = {"he_json": args.check, **compare_handeye(he, res)}
    _warn(out)
    return out


def _warn(out: dict[str, Any]) -> None:
    for prob in out["verdict"]["problems"]:
        print(f"cellctl: {prob['severity']}: {prob['message']}", file=sys.stderr)
