"""``cellctl pose``: the target's pose ``T_cam_target`` in one image, with a known camera."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "pose", help="target pose in the camera (T_cam_target) from one image",
        description="Detect the target in IMAGE and estimate T_cam_target (metres) with the camera of "
                    "cam.json; prints the pose, its reprojection RMS and its covariance.")
    p.add_argument("--camera", required=True, help="camera JSON (cam.json)")
    p.add_argument("--target", required=True, help="target YAML")
    p.add_argument("image", metavar="IMAGE")
    p.add_argument("--out", dest="out_json", help="write the pose JSON here too (input of cellctl measure)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.camera_io import read_camera
    from calibration.conic import circle_centre_bias_px
    from calibration.detect import detect_file
    from calibration.pnp import PoseEstimationError, estimate_pose
    from calibration.targets import CirclePlate, load_target

    camera, _ = read_camera(args.camera)
    target = load_target(args.target)
    det = detect_file(args.image, target)
    if not det.found:
        raise CommandError(f"{args.image}: target not found ({det.reason or 'no detection'})")
    if det.image_size not in ((0, 0), camera.size):
        raise CommandError(f"{args.image}: image is {det.image_size[0]}x{det.image_size[1]} but the camera "
                           f"was calibrated at {camera.width}x{camera.height}")
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    X = tp.xyz_m[[where[int(i)] for i in det.ids]]
    try:
        res = estimate_pose(camera, X, det.uv)
        if isinstance(target, CirclePlate) and det.uv_ellipse is not None:
            for _ in range(2):  # perspective bias from the known camera and the current pose
                bias = circle_centre_bias_px(camera, res.T_cam_target, X, target.radius_m)
                res = estimate_pose(camera, X, np.asarray(det.uv_ellipse) - bias)
    except PoseEstimationError as exc:
        raise CommandError(f"{args.image}: {exc}") from exc
    out = {"image": det.image, **res.to_json()}
    return out
