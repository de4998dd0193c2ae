"""The ``cellctl`` command: JSON results on stdout, logs on stderr, one-line errors.

Each command group lives in its own module here with a ``register(subparsers)`` function that
adds its parser and sets ``func`` (taking the parsed namespace, returning a JSON-able result or
``None``). ``COMMANDS`` names each top-level command, the module that registers it and its one-line
help; add a row to plug a new group in.

Start-up is lazy: ``main`` imports only the module of the command named on the command line (the
others appear in ``cellctl --help`` from the table alone), so ``cellctl --version``, ``--help`` and
the commands that talk to a running service load no numpy, OpenCV, numba or FastAPI
(``tests/cli/test_cli_startup.py``).
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

__all__ = ["COMMANDS", "COMMAND_MODULES", "CommandError", "build_parser", "emit", "main"]

COMMANDS: Final[dict[str, tuple[str, str]]] = {
    # command: (module under cellctl.cli that registers it, its help in `cellctl --help`)
    "serve": ("serve", "run the REST service"),
    "config": ("config_cmd", "configuration helpers"),
    "token": ("config_cmd", "manage REST tokens"),
    "grab": ("devices", "save one frame from a configured camera"),
    "robot": ("devices", "robot state, move, stop, resume on the running service"),
    "sim": ("sim", "the virtual cell"),
    "record": ("record", "record frames and robot states for replay"),
    "calib": ("calib", "calibrate camera, hand-eye, n-point"),
    "job": ("job", "run and follow routines on a running service"),
    "pose": ("pose", "target pose in the camera (T_cam_target) from one image or observed points"),
    "measure": ("measure", "image points to mm on a plane (image_points_to_world_plane)"),
    "map": ("map", "pixel -> robot-frame point (mm) with 1-sigma uncertainty"),
    "detect": ("detect", "detect calibration target points in images"),
    "target": ("target", "calibration target files"),
    "pick": ("pick", "teach part models and find parts"),
    "store": ("store_cmd", "back up / restore the calibration, recipe and audit store"),
    "warm-up": ("warm_up", "compile the compiled loops into numba's disk cache (set-up runs it)"),
}
COMMAND_MODULES: Final[tuple[str, ...]] = tuple(dict.fromkeys(module for module, _ in COMMANDS.values()))


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole command tree; with ``only`` (a command's name), that command's module alone is
    imported and registered, the others are listed by name and help (what ``cellctl --help`` shows)."""
    parser = argparse.ArgumentParser(
        prog="cellctl",
        description="Robot work-cell controller: acquisition, calibration and pick guidance.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging on stderr")
    parser.add_argument("--version", action="version", version=f"cellctl {cellctl.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    wanted = COMMAND_MODULES if only is None else ((COMMANDS[only][0],) if only in COMMANDS else ())
    registered: set[str] = set()
    for command, (module, helptext) in COMMANDS.items():
        if module in wanted and module not in registered:
            importlib.import_module(f"cellctl.cli.{module}").register(sub)
            registered.add(module)
        elif module not in wanted:
            sub.add_parser(command, help=helptext)  # listed only: its module is not imported for this call
    for leaf in _commands(parser):
        # `cellctl pick find ... -v` as well as `cellctl -v pick find ...`; SUPPRESS keeps a -v given
        # before the command when it is absent after it.
        leaf.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
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


def _command_named(argv: Sequence[str]) -> str | None:
    """The command the arguments name (the first that is not an option), or None (``--help``, ``--version``)."""
    for arg in argv:
        if arg == "--":
            return None
        if not arg.startswith("-"):
            return arg
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(only=_command_named(argv) or "")
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
