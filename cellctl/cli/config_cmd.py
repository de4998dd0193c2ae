"""``cellctl config default|check`` and ``cellctl token add|list|remove``.

Token edits keep ``cell.yaml`` as written (comments, order); a running service picks them up
without a restart (it re-reads the tokens when the file changes).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from cellctl.config import ROLE_RANK, load_config


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("config", help="configuration helpers")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    d = csub.add_parser("default", help="print the built-in virtual cell's cell.yaml")
    d.add_argument("--scene", choices=sorted(DEFAULT_SCENES), default="virtual-cell",
                   help="virtual-cell: the README tour's cell (eye-in-hand camera, two parts); production: a fixed "
                        "camera over a pick area of parts, a place grid and a sim gripper (docs/production.md); "
                        "fixed-camera: a camera fixed over a circle plate and a tool feature, for jog-to-mark with "
                        "its tool-centre step (docs/routines/jog-to-mark.md); conveyor: a belt past a fixed camera "
                        "into the robot's reach, a place grid and a sim gripper (docs/conveyor.md)")
    d.add_argument("--belt-speed-mm-s", type=_belt_speed, default=None, metavar="S",
                   help="the conveyor scene's belt speed in the printed config, mm/s (0-300; default 100)")
    d.add_argument("--motion-time-scale", type=_time_scale, default=None, metavar="S",
                   help="set the simulated robot's motion_time_scale (and a sim gripper's time_scale) in the printed "
                        "config: 1 real time, 0.25 four times faster, 0 instantaneous moves (default: the scene's, "
                        "real time)")
    d.set_defaults(func=print_default)
    c = csub.add_parser("check", help="validate a cell.yaml and print its devices")
    c.add_argument("--config", required=True)
    c.set_defaults(func=check)

    t: argparse.ArgumentParser = sub.add_parser(
        "token", help="manage REST tokens",
        description="Tokens are stored hashed in cell.yaml (auth.tokens); edits keep the file's comments. "
                    "A running service takes added and removed tokens into account at once (no restart).")
    tsub = t.add_subparsers(dest="token_command", metavar="ACTION", required=True)
    a = tsub.add_parser("add", help="add a token to cell.yaml (stored hashed) and print it once")
    a.add_argument("--config", required=True, help="the cell.yaml to edit")
    a.add_argument("--name", required=True, help="a name for the token (who or what uses it)")
    a.add_argument("--role", required=True, choices=sorted(ROLE_RANK, key=ROLE_RANK.__getitem__),
                   help="viewer < operator < engineer")
    a.add_argument("--out", dest="out_json", help="also write the JSON (with the token) to this file")
    a.set_defaults(func=add_token)
    ls = tsub.add_parser("list", help="the configured tokens' names and roles (never the tokens)")
    ls.add_argument("--config", required=True, help="the cell.yaml to read")
    ls.set_defaults(func=list_tokens)
    rm = tsub.add_parser("remove", help="revoke a token: remove it from cell.yaml (effective at once)")
    rm.add_argument("--config", required=True, help="the cell.yaml to edit")
    rm.add_argument("--name", required=True, help="the token's name (see `cellctl token list`)")
    rm.set_defaults(func=remove_token)


DEFAULT_SCENES = {"virtual-cell": "data/virtual-cell.yaml", "production": "data/production-cell.yaml",
                  "fixed-camera": "data/fixed-camera-cell.yaml", "conveyor": "data/conveyor-cell.yaml"}


def print_default(args: argparse.Namespace) -> None:
    from importlib import resources

    from cellctl.config import default_config_text

    scene = getattr(args, "scene", "virtual-cell")
    if scene == "virtual-cell":
        text = default_config_text()
    else:
        text = resources.files("cellctl").joinpath(DEFAULT_SCENES[scene]).read_text()
    scale = getattr(args, "motion_time_scale", None)
    text = text if scale is None else with_time_scale(text, scale)
    belt = getattr(args, "belt_speed_mm_s", None)
    if belt is not None:
        if scene != "conveyor":
            raise SystemExit("cellctl config default: --belt-speed-mm-s is for --scene conveyor")
        text = with_belt_speed(text, belt)
    sys.stdout.write(text)


def _belt_speed(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give the belt speed in mm/s (0-300)") from None
    if not 0.0 <= value <= 300.0:
        raise argparse.ArgumentTypeError(f"{text} mm/s is out of range; give 0-300 mm/s")
    return value


def with_belt_speed(text: str, speed_mm_s: float) -> str:
    """``text`` (a cell.yaml) with every sim conveyor's ``speed_mm_s`` set; comments and order kept."""
    import re

    out, n = re.subn(r"(\n\s+speed_mm_s: )[0-9.]+", lambda m: f"{m.group(1)}{speed_mm_s:g}", text)
    if n == 0:
        raise SystemExit("cellctl config default: the config has no conveyor speed to set")
    return out


def _time_scale(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give 0-10 (1: real time)") from None
    if not 0.0 <= value <= 10.0:
        raise argparse.ArgumentTypeError(f"{text} is out of range; give 0-10 (1: real time, 0: instantaneous)")
    return value


def with_time_scale(text: str, scale: float) -> str:
    """``text`` (a cell.yaml) with every sim robot's ``motion_time_scale`` and every sim gripper's
    ``time_scale`` set to ``scale``; comments and order kept."""
    import io

    from ruamel.yaml import YAML

    y = YAML()  # round-trip
    y.indent(mapping=2, sequence=4, offset=2)
    y.width = 4096
    y.representer.add_representer(type(None), lambda r, _: r.represent_scalar("tag:yaml.org,2002:null", "null"))
    data = y.load(text)
    for group, kind, key in (("robots", "sim", "motion_time_scale"), ("io", "sim_gripper", "time_scale")):
        for dev in (data.get(group) or {}).values():
            if dev.get("kind") == kind:
                dev.setdefault("settings", {})[key] = scale
    out = io.StringIO()
    y.dump(data, out)
    return out.getvalue()


def check(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_config(args.config)
    out: dict[str, Any] = {"ok": True, "cell_id": cfg.cell_id,
                           "cameras": {k: v.kind for k, v in cfg.cameras.items()},
                           "robots": {k: v.kind for k, v in cfg.robots.items()},
                           "io": {k: v.kind for k, v in cfg.io.items()}}
    if cfg.conveyors:  # a cell without a belt answers as before
        out["conveyors"] = {k: v.kind for k, v in cfg.conveyors.items()}
    return out


def add_token(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl import config_edit

    token = config_edit.add_token(args.config, args.name, args.role)
    return {"name": args.name, "role": args.role, "token": token,
            "note": "shown once; only its hash is stored in the config"}


def list_tokens(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl import config_edit

    return {"config": str(args.config), "tokens": config_edit.list_tokens(args.config)}


def remove_token(args: argparse.Namespace) -> dict[str, Any]:
    from cellctl import config_edit

    removed = config_edit.remove_token(args.config, args.name)
    return {"removed": removed, "note": "a running service refuses this token from its next request on"}
