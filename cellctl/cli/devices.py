"""``cellctl grab`` and ``cellctl robot state``: one device, opened for the call."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2

from cellctl.cell import Cell
from cellctl.cli.output import CommandError
from cellctl.config import load_config
from cellctl.robot_state import state_to_json


def register(sub: Any) -> None:
    g: argparse.ArgumentParser = sub.add_parser("grab", help="save one frame from a configured camera")
    g.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    g.add_argument("--camera", required=True, help="camera id in the config")
    g.add_argument("--out", required=True, help="image file to write (.png, .jpg, .bmp, .tif)")
    g.add_argument("--timeout-s", type=float, default=5.0)
    g.set_defaults(func=grab)

    r: argparse.ArgumentParser = sub.add_parser("robot", help="robot commands")
    rsub = r.add_subparsers(dest="robot_command", metavar="ACTION", required=True)
    s = rsub.add_parser("state", help="print a robot's state as JSON")
    s.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    s.add_argument("--robot", required=True, help="robot id in the config")
    s.set_defaults(func=robot_state)


def grab(args: argparse.Namespace) -> dict[str, Any]:
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
        raise CommandError(f"--out {out}: use an image file name ending in .png, .jpg, .bmp or .tif")
    cell = Cell(load_config(args.config))
    if args.camera not in cell.cameras:
        raise CommandError(f"no camera {args.camera!r} in the config; configured: {sorted(cell.cameras)}")
    slot = cell.cameras[args.camera]
    try:
        frame = slot.ensure_open().grab(timeout_s=args.timeout_s)
    finally:
        slot.close()
    if not cv2.imwrite(str(out), frame.pixels):
        raise CommandError(f"could not write {out}")
    return {"camera": args.camera, "file": str(out), "width": frame.size[0], "height": frame.size[1],
            "frame_id": frame.frame_id, "timestamp_s": frame.timestamp_s}


def robot_state(args: argparse.Namespace) -> dict[str, Any]:
    cell = Cell(load_config(args.config))
    if args.robot not in cell.robots:
        raise CommandError(f"no robot {args.robot!r} in the config; configured: {sorted(cell.robots)}")
    slot = cell.robots[args.robot]
    try:
        # The age is taken when the state is read, not after the adapter has closed.
        return state_to_json(args.robot, slot.ensure_open().state())
    finally:
        slot.close()
