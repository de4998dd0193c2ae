"""The ``cellctl`` command: JSON results on stdout, logs on stderr, one-line errors.

Each command group lives in its own module here with a ``register(subparsers)`` function that
adds its parser and sets ``func`` (taking the parsed namespace, returning a JSON-able result or
``None``). ``COMMAND_MODULES`` lists them; add a module's name to plug a new group in.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
from collections.abc import Sequence
from typing import Final

import cellctl
from cellctl.cli.output import CommandError, emit

__all__ = ["COMMAND_MODULES", "CommandError", "build_parser", "emit", "main"]

COMMAND_MODULES: Final[tuple[str, ...]] = (
    "serve",
    "config_cmd",
    "devices",
    "sim",
    "record",
    "calib",
    "job",
    "pose",
    "measure",
    "map",
    "detect",
    "target",
    "pick",
    "store_cmd",
    "warm_up",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cellctl",
        description="Robot work-cell controller: acquisition, calibration and pick guidance.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging on stderr")
    parser.add_argument("--version", action="version", version=f"cellctl {cellctl.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"cellctl.cli.{name}").register(sub)
    for command in _commands(parser):
        # `cellctl pick find ... -v` as well as `cellctl -v pick find ...`; SUPPRESS keeps a -v given
        # before the command when it is absent after it.
        command.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                             help="debug logging on stderr (also accepted before the command)")
    return parser


def _commands(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every parser below ``parser`` that takes arguments itself (the leaves of the command tree)."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases map to the same parser
                found += _commands(child) or [child]
    return found


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("httpx", "httpcore"):  # one line per request is noise on a command line
        logging.getLogger(noisy).setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    try:
        result = args.func(args)
        if result is not None:
            emit(result, getattr(args, "out_json", None))
        return 0
    except CommandError as exc:
        if args.verbose:  # -v: the traceback too, then the one-line error last
            traceback.print_exc(file=sys.stderr)
        print(f"cellctl: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except (ValueError, OSError, RuntimeError, TimeoutError) as exc:
        # Typed errors of our packages subclass these; their messages are meant for the user.
        if args.verbose:
            traceback.print_exc(file=sys.stderr)
        print(f"cellctl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cellctl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
