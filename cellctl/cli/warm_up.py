"""``cellctl warm-up``: compile the renderer's, matcher's and calibration solver's loops into numba's
disk cache now (``deploy/setup.sh`` runs it), so a fresh clone's first frame, search and calibration
load them instead of compiling, and the reports' plotting library once (its font cache) (``cellctl.warmup``)."""

from __future__ import annotations

import argparse
import os
from typing import Any


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "warm-up", help="compile the compiled loops into numba's disk cache (set-up runs it)",
        description="Compiles (or loads, when cached) the renderer's, the shape matcher's and the calibration "
                    "solver's numba loops, loads matplotlib for the reports (building its font cache on a fresh "
                    "machine), and prints the seconds each took and where the numba cache is. About a "
                    "minute of CPU on a cold cache, a few seconds once cached. The cache is beside each module "
                    "(__pycache__) unless NUMBA_CACHE_DIR names another folder; a service must see the same one.")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, metavar="N",
                   help="compile up to N parts at once, each in its own process (default: the number of CPUs)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from numba.core import config

    from cellctl.cli.output import CommandError
    from cellctl.warmup import warm_all

    if args.jobs < 1:
        raise CommandError(f"--jobs must be 1 or more (parts compiled at once), not {args.jobs}")
    seconds = warm_all(jobs=args.jobs)
    cache: str = getattr(config, "CACHE_DIR", "")  # numba's reading of NUMBA_CACHE_DIR (set at import)
    return {"seconds": seconds, "numba_cache": cache or "__pycache__ beside each module"}
