"""``cellctl sim truth`` (the virtual cell's ground truth) and ``cellctl sim ur`` (UR emulator)."""

from __future__ import annotations

import argparse
import importlib
from typing import Any

from cellctl.cli.output import CommandError
from cellctl.config import load_config, sim_settings


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("sim", help="the virtual cell")
    ssub = p.add_subparsers(dest="sim_command", metavar="ACTION", required=True)
    t = ssub.add_parser("truth", help="print the virtual cell's ground truth as JSON")
    t.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    t.set_defaults(func=truth)
    u = ssub.add_parser("ur", help="run a Universal Robots RTDE/dashboard emulator (ur_rtde connects to it)")
    u.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    u.set_defaults(func=ur)


def truth(args: argparse.Namespace) -> dict[str, Any]:
    from drivers.sim.world import world_for

    settings = sim_settings(load_config(args.config))
    if settings is None:
        raise CommandError("the config has no simulated (kind: sim) camera or robot; there is no truth to show")
    return world_for(settings.get("scene"), settings.get("seed")).truth()


def ur(args: argparse.Namespace) -> None:
    try:
        emulator = importlib.import_module("drivers.peers.ur_emulator")
    except ImportError as exc:
        raise CommandError(f"the UR emulator is not available in this installation ({exc})") from None
    emulator.run(host=args.host)
