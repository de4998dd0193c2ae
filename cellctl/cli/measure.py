"""``cellctl measure``: image points to metric points (mm) on a plane given by a pose JSON."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "measure", help="image points to mm on a plane (image_points_to_world_plane)",
        description="Map pixels U V to x_mm, y_mm on the plane z = 0 of the pose file's T_cam_target "
                    "(e.g. the output of cellctl pose).")
    p.add_argument("--camera", required=True, help="camera JSON (cam.json)")
    p.add_argument("--plane", required=True, help="pose JSON with T_cam_target (metres)")
    p.add_argument("coords", nargs="+", type=float, metavar="U V", help="pixel coordinates, pairs")
    p.add_argument("--out", dest="out_json", help="write the JSON here too")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> list[dict[str, float]]:
    from calibration.io import read_camera, read_pose
    from calibration.measure import image_to_plane

    if len(args.coords) % 2:
        raise CommandError(f"give pixel coordinates in pairs U V; got {len(args.coords)} numbers")
    camera, _ = read_camera(args.camera)
    T = read_pose(args.plane)
    uv = np.asarray(args.coords, dtype=np.float64).reshape(-1, 2)
    P = image_to_plane(camera, T, uv)
    return [{"u_px": float(u), "v_px": float(v), "x_mm": float(x * 1e3), "y_mm": float(y * 1e3)}
            for (u, v), (x, y, _) in zip(uv, P, strict=True)]
