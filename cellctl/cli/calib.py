"""``cellctl calib ...``: the calibration commands, one module per solver.

``CALIB_MODULES`` lists modules under ``cellctl/cli/`` whose ``register(calib_subparsers)`` adds
one ``calib`` subcommand (intrinsics, dlt, handeye, npoint).
"""

from __future__ import annotations

import argparse
import importlib
from typing import Any, Final

CALIB_MODULES: Final[tuple[str, ...]] = ("calib_intrinsics", "calib_dlt", "calib_export", "calib_handeye",
                                          "calib_npoint", "calib_tcp")


def register(sub: Any) -> None:
    parser: argparse.ArgumentParser = sub.add_parser("calib", help="calibrate camera, hand-eye, n-point")
    calib_sub = parser.add_subparsers(dest="calib_command", metavar="SOLVER", required=True)
    for name in CALIB_MODULES:
        importlib.import_module(f"cellctl.cli.{name}").register(calib_sub)
