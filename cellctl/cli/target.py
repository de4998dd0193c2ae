"""``cellctl target render --target T.yaml --out F.svg|png|pdf [--dpi N]``: a printable target.

The file is at true scale (SVG/PDF physical size exact; PNG with its DPI recorded) with a caption
line naming the type, the geometry and a check length to measure after printing. Prints a JSON
summary (file, page size in mm, the check length).
"""

from __future__ import annotations

import argparse
from typing import Any

from calibration.report import TargetPrintError, write_target
from calibration.targets import load_target
from cellctl.cli.output import CommandError
from cellctl.hints import target_print_message


def register(sub: Any) -> None:
    parser: argparse.ArgumentParser = sub.add_parser("target", help="calibration target files")
    tsub = parser.add_subparsers(dest="target_command", metavar="ACTION", required=True)
    render = tsub.add_parser("render", help="write a printable target at true scale (svg, pdf, png)")
    render.add_argument("--target", required=True, help="target description YAML (docs/targets.md)")
    render.add_argument("--out", required=True, help="output file: .svg, .pdf or .png")
    render.add_argument("--dpi", type=float, default=300.0, help="PNG resolution in dots per inch (default 300)")
    render.set_defaults(func=run_render)


def run_render(args: argparse.Namespace) -> dict[str, Any]:
    try:
        return write_target(load_target(args.target), args.out, args.dpi)
    except TargetPrintError as exc:
        raise CommandError(target_print_message(exc, {"dpi": "--dpi"})) from exc
