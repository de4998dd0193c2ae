"""``cellctl calib dlt``: a camera from one view of a non-coplanar 3D target (``points3d``)."""

from __future__ import annotations

import argparse
import csv
import logging
from pathlib import Path
from typing import Any

import numpy as np

from calibration.io import read_text
from cellctl.cli.output import CommandError

log = logging.getLogger("cellctl.calib.dlt")


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "dlt", help="camera from one view of a 3D target (DLT + refinement)",
        description="Camera intrinsics and pose from one image of a non-coplanar 3D target. "
                    "obs.csv has the header id,u_px,v_px; ids refer to the target's points_mm.")
    p.add_argument("--target", required=True, help="points3d target YAML")
    p.add_argument("--points", required=True, help="observations CSV: id,u_px,v_px")
    p.add_argument("--model", default="opencv5", choices=["opencv5", "division"])
    p.add_argument("--width", type=int, help="image width in px (default: from the principal point)")
    p.add_argument("--height", type=int, help="image height in px")
    p.add_argument("--no-distortion", action="store_true", help="fit a pinhole only")
    p.add_argument("--out", dest="out_json", help="write the camera JSON here too")
    p.set_defaults(func=run)


def read_observations(path: str) -> tuple[np.ndarray, np.ndarray]:
    p = Path(path)
    text = read_text(p, "observations", CommandError)
    rows = list(csv.DictReader(text.splitlines()))
    if not rows or not {"id", "u_px", "v_px"} <= set(rows[0]):
        raise CommandError(f"{p}: needs the header id,u_px,v_px and one row per observed point")
    ids, uv = [], []
    for n, r in enumerate(rows, start=2):
        try:
            ids.append(int(r["id"]))
            uv.append([float(r["u_px"]), float(r["v_px"])])
        except (TypeError, ValueError) as exc:
            raise CommandError(f"{p}: line {n}: id must be an integer and u_px, v_px numbers") from exc
    return np.array(ids, dtype=np.int64), np.array(uv, dtype=np.float64)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.pose import DLTError, calibrate_dlt
    from calibration.targets import Points3D, load_target

    target = load_target(args.target)
    if not isinstance(target, Points3D):
        raise CommandError(f"{args.target}: calib dlt needs a points3d target; for a planar "
                           f"{target.type} use calib intrinsics with several views")
    ids, uv = read_observations(args.points)
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    unknown = sorted({int(i) for i in ids if int(i) not in where})
    if unknown:
        raise CommandError(f"{args.points}: ids {unknown[:5]} are not in the target's points_mm")
    if (args.width is None) != (args.height is None):
        raise CommandError("give both --width and --height, or neither")
    size = (args.width, args.height) if args.width else None
    if size is None:
        log.warning("image size not given (--width/--height): assuming twice the principal point")
    try:
        res = calibrate_dlt(tp.xyz_m[[where[int(i)] for i in ids]], uv, size, args.model,
                            distortion=not args.no_distortion)
    except DLTError as exc:
        raise CommandError(f"DLT failed: {exc}") from exc
    return res.to_json()
