"""``cellctl job run NAME [--param k=v ...] [--follow]``: run a routine on a running service.

Talks to ``cellctl serve`` over HTTP (``--url``, default http://127.0.0.1:8080) with a bearer
token (``--token``, ``$CELLCTL_TOKEN``, or the session token file of a local lab service). With
``--follow`` it prints a progress bar on stderr from the job's event stream and, for routines
that wait for the operator (jog-to-mark), asks on the terminal before each record.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from cellctl.cli.output import CommandError, emit
from cellctl.paths import data_dir


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("job", help="run and follow routines on a running service")
    jsub = p.add_subparsers(dest="job_command", metavar="ACTION", required=True)
    r = jsub.add_parser("run", help="start a routine (intrinsics-capture, handeye-capture, jog-to-mark, verify)")
    r.add_argument("name")
    r.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="routine parameter (JSON value or plain string); repeatable")
    r.add_argument("--follow", action="store_true", help="show progress until the job ends")
    r.add_argument("--url", default=os.environ.get("CELLCTL_URL", "http://127.0.0.1:8080"))
    r.add_argument("--token", default=os.environ.get("CELLCTL_TOKEN"))
    r.add_argument("--out", dest="out_json", help="also write the final job JSON to this file")
    r.set_defaults(func=run)
    s = jsub.add_parser("status", help="print a job")
    s.add_argument("job_id")
    s.add_argument("--url", default=os.environ.get("CELLCTL_URL", "http://127.0.0.1:8080"))
    s.add_argument("--token", default=os.environ.get("CELLCTL_TOKEN"))
    s.set_defaults(func=status)


def _token(args: argparse.Namespace) -> str:
    if args.token:
        return str(args.token)
    files = sorted(data_dir().glob("*.session-token"), key=lambda f: f.stat().st_mtime, reverse=True)
    if files:
        return files[0].read_text().strip()
    raise CommandError("no token: give --token or set CELLCTL_TOKEN (make one with `cellctl token add`)")


def _params(pairs: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise CommandError(f"--param {pair!r}: use KEY=VALUE, e.g. --param views=14")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _client(args: argparse.Namespace) -> Any:
    import httpx

    return httpx.Client(base_url=args.url, headers={"Authorization": f"Bearer {_token(args)}"}, timeout=30.0)


def _check(r: Any) -> dict[str, Any]:
    if r.status_code >= 400:
        try:
            err = r.json().get("error", {})
            msg = f"{err.get('code')}: {err.get('message')}"
        except ValueError:
            msg = r.text[:200]
        raise CommandError(f"the service answered {r.status_code} ({msg})")
    body: dict[str, Any] = r.json()
    return body


def run(args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    try:
        with _client(args) as http:
            job = _check(http.post(f"/routines/{args.name}", json=_params(args.param)))
            if not args.follow:
                return job
            _follow(http, job["id"])
            final = _check(http.get(f"/jobs/{job['id']}"))
    except httpx.HTTPError as exc:
        raise CommandError(f"cannot reach the service at {args.url} ({exc}); is `cellctl serve` running?") from None
    if final["state"] != "succeeded":
        emit(final, args.out_json)
        raise CommandError(f"job {final['id']} ({final['name']}) {final['state']}: {final.get('error') or ''}",
                           exit_code=1)
    return final


def _bar(progress: float, message: str) -> None:
    n = int(progress * 30)
    sys.stderr.write(f"\r[{'#' * n}{'.' * (30 - n)}] {progress * 100:5.1f}% {message[:70]:<70}")
    sys.stderr.flush()


def _follow(http: Any, job_id: str) -> None:
    event = ""
    with http.stream("GET", f"/jobs/{job_id}/events", timeout=None) as stream:
        for line in stream.iter_lines():
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                data = json.loads(line[6:])
                if event == "progress":
                    _bar(float(data.get("progress", 0.0)), str(data.get("message", "")))
                elif event == "input_needed":
                    sys.stderr.write(f"\n{data.get('instruction', 'input needed')} — press Enter to record ")
                    sys.stderr.flush()
                    if sys.stdin.readline() == "":
                        raise CommandError("no terminal input to record with; cancel the job or record over HTTP")
                    _check(http.post(f"/jobs/{job_id}/record"))
                elif event == "state":
                    sys.stderr.write(f"\n{data.get('state')}: {data.get('message')}\n")
                    return


def status(args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    try:
        with _client(args) as http:
            return _check(http.get(f"/jobs/{args.job_id}"))
    except httpx.HTTPError as exc:
        raise CommandError(f"cannot reach the service at {args.url} ({exc})") from None
