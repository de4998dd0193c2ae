"""``cellctl calib tcp``: the tool centre for a fixed camera from turning the tool about z.

``rot.csv``: header ``u_px,v_px,x_mm,y_mm,rz_deg`` — the image of one feature carried by the tool
while the robot, flange at ``(x_mm, y_mm)``, turns it to ``rz_deg`` about the base z axis; rows
at one flange position form one circle (at least 3 angles over at least 30 deg; 7 over 90-180 deg
recommended), one or more positions. ``np.json`` maps the pixels to mm (``cellctl calib npoint``).
Prints ``tcp.json``: ``offset_mm`` (the feature's offset from the flange axis, tool x/y along base
x/y at rz = 0), ``rotation_centre_px`` per flange position, ``rms_mm`` and the 1-sigma
``uncertainty.offset_mm`` (``calibration.handeye.tool_centre``).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any, Final

import numpy as np

from cellctl.cli.output import CommandError

COLUMNS: Final = ("u_px", "v_px", "x_mm", "y_mm", "rz_deg")


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "tcp", help="tool centre (feature offset from the flange axis) from turning the tool about z",
        description="Fit the circle a tool feature describes while the tool turns about z at one or more "
                    "flange positions, through the N-point map (mm): the feature's offset from the flange axis "
                    "in the tool frame with its 1-sigma. rot.csv: u_px,v_px,x_mm,y_mm,rz_deg.")
    p.add_argument("--npoint", required=True, help="np.json of the fixed camera (cellctl calib npoint)")
    p.add_argument("--rotations", required=True, help="rot.csv: u_px,v_px,x_mm,y_mm,rz_deg, one row per angle")
    p.add_argument("--out", dest="out_json", help="write tcp.json here too")
    p.set_defaults(func=run)


def read_rotations(path: str) -> np.ndarray:
    """(N, 5) rows of ``rot.csv`` in the column order of ``COLUMNS``."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise CommandError(f"{p}: cannot read rotations ({exc.strerror})") from exc
    rows = list(csv.DictReader(text.splitlines()))
    if not rows or not set(COLUMNS) <= set(rows[0]):
        raise CommandError(f"{p}: needs the header {','.join(COLUMNS)} and one row per tool angle")
    out = []
    for n, r in enumerate(rows, start=2):
        try:
            vals = [float(r[c]) for c in COLUMNS]
        except (TypeError, ValueError) as exc:
            raise CommandError(f"{p}: line {n}: {', '.join(COLUMNS)} must be numbers") from exc
        if not np.all(np.isfinite(vals)):
            raise CommandError(f"{p}: line {n}: NaN or infinity")
        out.append(vals)
    return np.array(out, dtype=np.float64)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.handeye import ToolCentreError, fit_tool_centre
    from calibration.npoint import NPointError, NPointResult

    try:
        data = json.loads(Path(args.npoint).read_text())
    except OSError as exc:
        raise CommandError(f"{args.npoint}: cannot read the N-point calibration ({exc.strerror})") from exc
    except json.JSONDecodeError as exc:
        raise CommandError(f"{args.npoint}: not valid JSON ({exc.msg})") from exc
    try:
        npoint = NPointResult.from_json(data)
    except (NPointError, TypeError) as exc:
        raise CommandError(f"{args.npoint}: {exc} (make it with cellctl calib npoint)") from exc
    rows = read_rotations(args.rotations)
    try:
        res = fit_tool_centre(rows[:, 0:2], rows[:, 2:4], rows[:, 4], npoint)
    except ToolCentreError as exc:
        raise CommandError(f"{args.rotations}: {exc}") from exc
    return res.to_json()
