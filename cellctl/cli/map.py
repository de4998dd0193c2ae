"""``cellctl map``: a pixel to a robot-frame point in mm with its 1-σ uncertainty.

The answer has ``sigma_mm: [x, y, z]`` like ``POST /map`` (and the ``sigma`` object with
``total_mm`` too). A robot pose whose translation looks like millimetres and a pixel outside the
calibrated image are refused.

Works with an N-point map (``np.json``) or a hand-eye calibration (``he.json``; needs the working
plane's height ``--plane-z-mm`` in the base frame and, eye-in-hand, ``--robot-pose`` at capture
in UR's form ``x,y,z,rx,ry,rz`` (metres, rotation vector in radians)).

A hand-eye maps through the camera it was solved with (``he.json["camera"]``: the jointly refined
intrinsics when the solve refined them). ``--camera`` is for a he.json without a camera; with a
he.json that carries one it is refused (exit 2, the reason in one line) unless it is the same
camera within ``calibration.io.SAME_CAMERA_TOLERANCE_PX``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError
from cellctl.hints import mapping_message
from cellctl.numbers import pixel_problem, pose_ur_problem

# The mapping library's inputs as this command's options (its messages name the library's arguments).
FLAGS = {"plane_z_mm": "--plane-z-mm Z (base frame, mm)", "camera": "--camera cam.json",
         "robot_pose": "--robot-pose x,y,z,rx,ry,rz (metres and rotation vector as UR reports it)"}
FLAGS_TO_CHECK = {"plane_z_mm": "--plane-z-mm (base frame, mm)", "robot_pose": "--robot-pose (eye-in-hand)"}


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "map", help="pixel -> robot-frame point (mm) with 1-sigma uncertainty",
        description="Map an image point through np.json (n-point) or he.json (hand-eye) to the robot base frame.")
    p.add_argument("--calib", required=True, help="np.json or he.json")
    p.add_argument("--camera", help="cam.json (only for a he.json without its own camera; a he.json maps through "
                                    "the camera it was solved with, and another one is refused)")
    p.add_argument("--plane-z-mm", type=float, help="working-plane height in the robot base frame, mm")
    p.add_argument("--robot-pose", help="eye-in-hand: T_base_tool at capture as x,y,z,rx,ry,rz (m, rad)")
    p.add_argument("--pixel-sigma-px", type=float, help="pixel noise of the query point, 1-sigma (px)")
    p.add_argument("u", type=float, metavar="U", help="pixel column")
    p.add_argument("v", type=float, metavar="V", help="pixel row")
    p.add_argument("--out", dest="out_json", help="write the result JSON here too")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.io import read_json
    from calibration.measure import MappingError, pixel_to_robot

    path = Path(args.calib)
    calib = read_json(path, "a calibration file (np.json or he.json)", CommandError)
    camera = None
    if args.camera:
        from calibration.io import read_camera

        camera = read_camera(args.camera)[0]
        _check_own_camera(calib, camera, args.camera, str(path))
    pose = None
    if args.robot_pose is not None:
        try:
            pose = [float(x) for x in args.robot_pose.split(",")]
        except ValueError:
            raise CommandError(f"--robot-pose must be six numbers x,y,z,rx,ry,rz, got {args.robot_pose!r}") from None
        if len(pose) != 6:
            raise CommandError(f"--robot-pose must be six numbers x,y,z,rx,ry,rz (m, rad), got {len(pose)}")
        problem = pose_ur_problem(pose, "--robot-pose")
        if problem:
            raise CommandError(problem + "; e.g. --robot-pose 0.4,0,0.55,3.1416,0,0")
    size = _image_size(calib, camera)
    problem = pixel_problem(args.u, args.v, size, "the calibrated camera", names=("U", "V"))
    if problem:
        raise CommandError(problem)
    try:
        out = pixel_to_robot(calib, [args.u, args.v], camera=camera, plane_z_mm=args.plane_z_mm, robot_pose=pose,
                             pixel_sigma_px=args.pixel_sigma_px).to_json()
    except MappingError as exc:
        raise CommandError(mapping_message(exc, FLAGS_TO_CHECK if exc.need == "check" else FLAGS)) from None
    out["u_px"], out["v_px"] = args.u, args.v
    # The same key and shape as the REST answer of POST /map: [x, y, z] in mm (z absent for a 2-D map).
    sig = out.get("sigma", {})
    out["sigma_mm"] = [sig[k] for k in ("x_mm", "y_mm", "z_mm") if k in sig]
    return out


def _check_own_camera(calib: dict[str, Any], camera: Any, camera_path: str, calib_path: str) -> None:
    """Refuse a ``--camera`` that is not the camera the hand-eye in ``calib`` was solved with."""
    from calibration.io import CameraFileError, camera_mismatch, handeye_camera

    if "setup" not in calib:  # an n-point map: its --camera only removes distortion
        return
    try:
        own = handeye_camera(calib, calib_path)
    except CameraFileError as exc:
        raise CommandError(str(exc)) from None
    if own is None:
        return
    why = camera_mismatch(own, camera, f"--camera {camera_path}")
    if why is not None:
        refined = " (it refined the intrinsics jointly)" if calib.get("intrinsics_refined") else ""
        raise CommandError(f"{calib_path} carries the camera it was solved with{refined} and maps only through it: "
                           f"{why}; leave --camera out, or solve the hand-eye again with this camera")


def _image_size(calib: dict[str, Any], camera: Any) -> tuple[int, int] | None:
    """The image size the pixel must lie in: the camera's, else what the calibration file says."""
    if camera is not None:
        return tuple(camera.size)  # type: ignore[return-value]
    for holder in (calib.get("camera"), calib):
        if isinstance(holder, dict) and isinstance(holder.get("width"), int) and isinstance(holder.get("height"), int):
            return holder["width"], holder["height"]
    size = calib.get("image_size")
    if isinstance(size, list) and len(size) == 2 and all(isinstance(x, int) for x in size):
        return size[0], size[1]
    return None
