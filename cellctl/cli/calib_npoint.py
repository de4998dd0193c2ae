"""``cellctl calib npoint``: the jog-to-mark image→robot mapping from ``pairs.csv``.

``pairs.csv`` (docs/datasets.md): header ``u_px,v_px,x_mm,y_mm``. Prints ``np.json``
(docs/cli.md): the model, ``H`` mapping ``[u, v, 1]`` to ``[x_mm, y_mm, 1]``, the RMS,
HALCON's affine parameters, each model's leave-one-out error and the predicted error over the
field. With ``--camera`` the pixels are undistorted first (and the camera is stored in np.json so
that ``cellctl map`` undistorts the same way).
"""

from __future__ import annotations

import argparse
from typing import Any

from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "npoint", help="jog-to-mark (N-point) image-to-robot mapping",
        description="Fit the image->robot map from pairs.csv (u_px,v_px,x_mm,y_mm). Without --model the "
                    "model is chosen by leave-one-out cross-validation.")
    p.add_argument("--pairs", required=True, help="pairs.csv (u_px,v_px,x_mm,y_mm)")
    p.add_argument("--model", choices=["affine", "similarity", "homography"],
                   help="force a model (default: chosen by leave-one-out)")
    p.add_argument("--camera", help="cam.json: undistort the pixels first")
    p.add_argument("--out", dest="out_json", help="write np.json here too")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.io import read_pairs_csv
    from calibration.npoint import fit_npoint

    uv, xy = read_pairs_csv(args.pairs)
    camera = None
    if args.camera:
        from calibration.io import read_camera

        camera = read_camera(args.camera)[0]
    try:
        return fit_npoint(uv, xy, args.model, camera).to_json()
    except ValueError as exc:
        raise CommandError(f"{args.pairs}: {exc}") from exc
