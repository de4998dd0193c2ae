"""``cellctl config default`` and ``cellctl token add``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import yaml

from cellctl.auth import hash_token, new_token
from cellctl.cli.output import CommandError
from cellctl.config import ROLE_RANK, load_config, parse_config


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("config", help="configuration helpers")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    d = csub.add_parser("default", help="print the built-in virtual cell's cell.yaml")
    d.set_defaults(func=print_default)
    c = csub.add_parser("check", help="validate a cell.yaml and print its devices")
    c.add_argument("--config", required=True)
    c.set_defaults(func=check)

    t: argparse.ArgumentParser = sub.add_parser("token", help="manage REST tokens")
    tsub = t.add_subparsers(dest="token_command", metavar="ACTION", required=True)
    a = tsub.add_parser("add", help="add a token to cell.yaml (stored hashed) and print it once")
    a.add_argument("--config", required=True)
    a.add_argument("--name", required=True)
    a.add_argument("--role", required=True, choices=sorted(ROLE_RANK, key=ROLE_RANK.__getitem__))
    a.add_argument("--out", dest="out_json", help="also write the JSON (with the token) to this file")
    a.set_defaults(func=add_token)


def print_default(args: argparse.Namespace) -> None:
    from cellctl.config import default_config_text

    sys.stdout.write(default_config_text())


def check(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_config(args.config)
    return {"ok": True, "cell_id": cfg.cell_id,
            "cameras": {k: v.kind for k, v in cfg.cameras.items()},
            "robots": {k: v.kind for k, v in cfg.robots.items()},
            "io": {k: v.kind for k, v in cfg.io.items()}}


def add_token(args: argparse.Namespace) -> dict[str, Any]:
    path = Path(args.config)
    load_config(path)  # refuse to touch a config that does not validate
    data = yaml.safe_load(path.read_text()) or {}
    tokens = data.setdefault("auth", {}).setdefault("tokens", []) or []
    if any(t.get("name") == args.name for t in tokens):
        raise CommandError(f"{path}: a token named {args.name!r} exists already; choose another name")
    token = new_token()
    tokens.append({"name": args.name, "role": args.role, "sha256": hash_token(token)})
    data["auth"]["tokens"] = tokens
    parse_config(data, str(path))
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    tmp.replace(path)
    return {"name": args.name, "role": args.role, "token": token,
            "note": "shown once; only its hash is stored in the config"}
