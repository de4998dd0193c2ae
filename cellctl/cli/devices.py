"""``cellctl grab`` and ``cellctl robot state|move|stop|resume``.

``robot state``, ``move``, ``stop`` and ``resume`` ask the running ``cellctl serve`` (``--url``,
``--token`` as for ``cellctl job``): the service owns the robot, its motion checks, Stop latch and
audit log, so "where is the robot?" is answered for the cell the command names. Only when asked by
name (``robot state --config cell.yaml`` or ``--local``) is a robot opened directly for the call, and
the command then says so on stderr. ``grab`` opens its camera directly (no service may be driving it).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from cellctl.cli.job import TOKEN_HELP, URL_HELP
from cellctl.cli.output import CommandError


def register(sub: Any) -> None:
    g: argparse.ArgumentParser = sub.add_parser("grab", help="save one frame from a configured camera")
    g.add_argument("--config", help="cell.yaml (default: the built-in virtual cell)")
    g.add_argument("--camera", required=True, help="camera id in the config")
    g.add_argument("--out", required=True, help="image file to write (.png, .jpg, .bmp, .tif)")
    g.add_argument("--timeout-s", type=float, default=5.0)
    g.set_defaults(func=grab)

    r: argparse.ArgumentParser = sub.add_parser("robot", help="robot state, move, stop, resume on the running service")
    rsub = r.add_subparsers(dest="robot_command", metavar="ACTION", required=True)
    s = rsub.add_parser("state", help="print a robot's state as JSON from the running service (--config: the device)",
                        description="Asks the running service (GET /robots/ID/state at --url: the pose it serves and "
                                    "whether a Stop latches the robot). Only with --config (or --local: the built-in "
                                    "virtual cell) is the robot opened directly for this call, bypassing any service "
                                    "(no service may be driving it); the command then says so on stderr.")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--url", default=None, help=URL_HELP)
    where.add_argument("--config", help="open the robot of this cell.yaml directly instead of asking the service")
    where.add_argument("--local", action="store_true",
                       help="open the built-in virtual cell's robot directly instead of asking the service")
    s.add_argument("--token", default=None, help=TOKEN_HELP)
    s.add_argument("--robot", required=True, help="robot id in the config")
    s.set_defaults(func=robot_state)

    m = rsub.add_parser("move", help="move the tool on the running service (engineer): to a named pose or a UR pose",
                        description="POST /robots/ID/move on the running service: a checked linear move (envelope, "
                                    "tool cone, speed), refused while another motion owns the robot or a Stop "
                                    "latches it. Named poses are the config's robots.<id>.poses.")
    m.add_argument("--robot", required=True, help="robot id in the config")
    to = m.add_mutually_exclusive_group(required=True)
    to.add_argument("--named-pose", help="a pose named in the config (robots.<id>.poses), e.g. home")
    to.add_argument("--pose-ur", help="x,y,z,rx,ry,rz: metres and a rotation vector in radians (base frame)")
    m.add_argument("--speed-m-s", type=float, default=None, help="tool speed, m/s (default: the service's, 0.05)")
    _service_args(m)
    m.set_defaults(func=robot_move)
    for name, helptext in (("stop", "halt the robot now and latch it (operator); the running sequence is aborted"),
                           ("resume", "clear the Stop latch (engineer): the robot may move again")):
        a = rsub.add_parser(name, help=helptext + " - on the running service", description=helptext + ".")
        a.add_argument("--robot", required=True, help="robot id in the config")
        _service_args(a)
        a.set_defaults(func=robot_stop if name == "stop" else robot_resume)


def _service_args(p: argparse.ArgumentParser) -> None:
    from cellctl.cli.job import _service_args as service_args

    service_args(p)


def grab(args: argparse.Namespace) -> dict[str, Any]:
    import cv2

    from cellctl.cell import Cell
    from cellctl.config import load_config

    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
        raise CommandError(f"--out {out}: use an image file name ending in .png, .jpg, .bmp or .tif")
    cell = Cell(load_config(args.config))
    if args.camera not in cell.cameras:
        raise CommandError(f"no camera {args.camera!r} in the config; configured: {sorted(cell.cameras)}")
    slot = cell.cameras[args.camera]
    try:
        frame = slot.ensure_open().grab(timeout_s=args.timeout_s)
    finally:
        slot.close()
    if not cv2.imwrite(str(out), frame.pixels):
        raise CommandError(f"could not write {out}")
    return {"camera": args.camera, "file": str(out), "width": frame.size[0], "height": frame.size[1],
            "frame_id": frame.frame_id, "timestamp_s": frame.timestamp_s}


def robot_state(args: argparse.Namespace) -> dict[str, Any]:
    if not (args.config or args.local):
        args.url = args.url or os.environ.get("CELLCTL_URL", "http://127.0.0.1:8080")
        args.token = args.token or os.environ.get("CELLCTL_TOKEN")
        return _service(args, "GET", f"/robots/{args.robot}/state")
    if args.token is not None:
        raise CommandError("--token belongs to the service form (--url); with --config/--local the device is read "
                           "directly")
    from cellctl.cell import Cell
    from cellctl.config import load_config
    from cellctl.robot_state import state_to_json

    cell = Cell(load_config(args.config))
    if args.robot not in cell.robots:
        raise CommandError(f"no robot {args.robot!r} in the config; configured: {sorted(cell.robots)}")
    source = args.config or "the built-in virtual cell"
    print(f"cellctl: reading robot {args.robot} of {source} directly, not through a service (a running "
          "service's robot and its Stop latch are not seen; leave out --config/--local to ask the service)",
          file=sys.stderr, flush=True)
    slot = cell.robots[args.robot]
    try:
        # The age is taken when the state is read, not after the adapter has closed.
        return state_to_json(args.robot, slot.ensure_open().state())
    finally:
        slot.close()


def _service(args: argparse.Namespace, method: str, path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
    import httpx

    from cellctl.cli.job import _check, _client

    try:
        with _client(args) as http:
            return _check(http.request(method, path, json=body), getattr(args, "token_file", None))
    except httpx.HTTPError as exc:
        raise CommandError(f"cannot reach the service at {args.url} ({exc}); is `cellctl serve` running?") from None


def robot_move(args: argparse.Namespace) -> dict[str, Any]:
    body: dict[str, Any] = {}
    if args.named_pose is not None:
        body["named_pose"] = args.named_pose
    else:
        try:
            pose = [float(x) for x in args.pose_ur.split(",")]
        except ValueError:
            raise CommandError(f"--pose-ur must be six numbers x,y,z,rx,ry,rz, got {args.pose_ur!r}") from None
        if len(pose) != 6:
            raise CommandError(f"--pose-ur must be six numbers x,y,z,rx,ry,rz (m, rad), got {len(pose)}")
        from cellctl.numbers import pose_ur_problem

        problem = pose_ur_problem(pose, "--pose-ur")
        if problem:
            raise CommandError(problem + "; e.g. --pose-ur 0.4,0,0.55,3.1416,0,0")
        body["pose_ur"] = dict(zip(("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"), pose, strict=True))
    if args.speed_m_s is not None:
        body["speed_m_s"] = args.speed_m_s
    return _service(args, "POST", f"/robots/{args.robot}/move", body)


def robot_stop(args: argparse.Namespace) -> dict[str, Any]:
    return _service(args, "POST", f"/robots/{args.robot}/stop")


def robot_resume(args: argparse.Namespace) -> dict[str, Any]:
    return _service(args, "POST", f"/robots/{args.robot}/resume")
