"""``cellctl pose``: the target's pose ``T_cam_target`` from one image or observed points, with a known camera."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "pose", help="target pose in the camera (T_cam_target) from one image or observed points",
        description="Detect the target in IMAGE (or read its observed points from --points obs.csv) and "
                    "estimate T_cam_target (metres) with the camera of cam.json; prints the pose, its "
                    "reprojection RMS, its covariance and the method used.")
    p.add_argument("--camera", required=True, help="camera JSON (cam.json)")
    p.add_argument("--target", required=True, help="target YAML")
    p.add_argument("image", metavar="IMAGE", nargs="?", help="image of the target (or give --points)")
    p.add_argument("--points", help="observed target points instead of an image: CSV with the header "
                                    "id,u_px,v_px (ids as cellctl detect reports them)")
    p.add_argument("--method", default="auto", choices=["auto", "rpnp", "sqpnp", "ippe", "epnp"],
                   help="initial solver, each refined on pixels: auto (SQPnP, plus IPPE for a planar target), "
                        "rpnp (Li, Xu, Xie 2012, non-iterative), sqpnp, ippe (planar targets), epnp "
                        "(default auto)")
    p.add_argument("--out", dest="out_json", help="write the pose JSON here too (input of cellctl measure)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.detect import circle_centre_bias_px, detect_file
    from calibration.io import read_camera
    from calibration.pose import PoseEstimationError, estimate_pose_by
    from calibration.targets import CirclePlate, load_target

    if (args.image is None) == (args.points is None):
        raise CommandError("give either IMAGE or --points obs.csv (one of them)")
    camera, _ = read_camera(args.camera)
    target = load_target(args.target)
    if args.points is not None:
        return _from_points(args, camera, target)
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
        res = estimate_pose_by(camera, X, det.uv, args.method)
        if isinstance(target, CirclePlate) and det.uv_ellipse is not None:
            for _ in range(2):  # perspective bias from the known camera and the current pose
                bias = circle_centre_bias_px(camera, res.T_cam_target, X, target.radius_m)
                res = estimate_pose_by(camera, X, np.asarray(det.uv_ellipse) - bias, args.method)
    except PoseEstimationError as exc:
        raise CommandError(f"{args.image}: {exc}") from exc
    out = {"image": det.image, **res.to_json(), "requested_method": args.method}
    return out


def _from_points(args: argparse.Namespace, camera: Any, target: Any) -> dict[str, Any]:
    """The pose from observed points (``id,u_px,v_px``); ids must be points of the target."""
    from calibration.pose import PoseEstimationError, estimate_pose_by
    from cellctl.cli.calib_dlt import read_observations

    ids, uv = read_observations(args.points)
    if len(set(ids.tolist())) != len(ids):
        raise CommandError(f"{args.points}: an id appears more than once; each target point is observed once")
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    unknown = sorted({int(i) for i in ids if int(i) not in where})
    if unknown:
        raise CommandError(f"{args.points}: ids {unknown[:5]} are not points of the target {args.target}")
    X = tp.xyz_m[[where[int(i)] for i in ids]]
    try:
        res = estimate_pose_by(camera, X, uv, args.method)
    except PoseEstimationError as exc:
        raise CommandError(f"{args.points}: {exc}") from exc
    return {"points": args.points, **res.to_json(), "requested_method": args.method}
