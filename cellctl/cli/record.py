"""``cellctl record``: frames and robot states of a configured cell into a recording folder."""

from __future__ import annotations

import argparse
import logging
import time
from typing import Any

from cellctl.cell import Cell
from cellctl.cli.output import CommandError
from cellctl.config import load_config
from drivers.recording import RecordingWriter

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("record", help="record frames and robot states for replay")
    p.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    p.add_argument("--out", required=True, help="new folder for the recording")
    p.add_argument("--frames", type=int, required=True, help="how many frames per camera")
    p.add_argument("--interval-s", type=float, default=0.0, help="pause between frames, seconds")
    p.set_defaults(func=record)


def record(args: argparse.Namespace) -> dict[str, Any]:
    if args.frames < 1:
        raise CommandError("--frames must be at least 1")
    cell = Cell(load_config(args.config))
    if not cell.cameras and not cell.robots:
        raise CommandError("the config has no cameras or robots to record")
    writer = RecordingWriter(args.out)
    try:
        cams = {k: s.ensure_open() for k, s in cell.cameras.items()}
        robots = {k: s.ensure_open() for k, s in cell.robots.items()}
        for i in range(args.frames):
            for rid, robot in robots.items():
                writer.add_state(rid, robot.state())
            for cid, cam in cams.items():
                writer.add_frame(cid, cam.grab())
            log.info("recorded %d/%d", i + 1, args.frames)
            if args.interval_s > 0 and i + 1 < args.frames:
                time.sleep(args.interval_s)
    finally:
        manifest = writer.close()
        cell.close()
    return {"out": args.out, **manifest}
