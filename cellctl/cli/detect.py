"""``cellctl detect --target T.yaml IMAGE... [--out F.json]``: target points per image.

Prints ``[{"image", "found", "points": [{"id", "u_px", "v_px"[, "u_ellipse_px", "v_ellipse_px"]}],
"reason"?, "width", "height", "quality"?}]`` (docs/cli.md). A corrupt or unreadable
image or a bad target file is an error (one line, exit code 2); an image in which the target is
not found is a result with ``"found": false`` and the reason.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from calibration.detect import detect_file
from calibration.targets import load_target
from cellctl.cli.output import CommandError

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    parser: argparse.ArgumentParser = sub.add_parser(
        "detect", help="detect calibration target points in images",
        description="Detect a calibration target's points (ids, sub-pixel u_px/v_px) in each image.")
    parser.add_argument("--target", required=True, help="target description YAML (docs/targets.md)")
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="image files (png, jpg, bmp, tif) or folders of them (read in sorted name order)")
    parser.add_argument("--out", dest="out_json", help="also write the JSON result to this file")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    target = load_target(args.target)
    if target.type == "points3d":
        raise CommandError(f"{args.target}: points3d targets have no printed pattern to detect; "
                           "give their image points as obs.csv (id,u_px,v_px) instead")
    from cellctl.cli.calib_intrinsics import _image_files  # the same folder rule as calib intrinsics

    results = []
    for image in _image_files(args.images):
        det = detect_file(Path(image), target)
        det.image = str(image)
        log.info("%s: %s", image, f"{len(det.ids)} points" if det.found else f"not found ({det.reason})")
        results.append(det.to_json())
    return results
