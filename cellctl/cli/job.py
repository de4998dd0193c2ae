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
import textwrap
from typing import Any, TextIO

from cellctl.cli.output import CommandError, emit
from cellctl.paths import data_dir

VERDICT_NOT_OK_EXIT = 3
"""``job run --follow``: the job succeeded but its verdict is NOT OK (1: it failed, was cancelled or stopped)."""
URL_HELP = "the service's base URL (default: $CELLCTL_URL or http://127.0.0.1:8080)"
TOKEN_HELP = ("bearer token (default: $CELLCTL_TOKEN, else the session-token file of a local lab service "
              "started without tokens)")


class _HelpWithParams(argparse.Action):
    """``job run NAME --help``: the usual help, then that routine's parameters (all routines' when no
    known NAME came before ``--help``); read from their models only when asked, so other commands do
    not import the routines."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs: Any) -> None:
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0,
                         help="show this help with the routine's parameters (NAME --help: that routine's only)")

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        parser.epilog = routine_params_help(getattr(namespace, "name", None))
        parser.print_help()
        parser.exit()


def routine_params_help(only: str | None = None) -> str:
    """The routines' parameters as text: name, type, default, range and what it means (with units).

    ``only``: that routine alone when it is one (else every routine, after a line naming the unknown one).
    """
    from cellctl.routines import MOVES_ROBOT, ROUTINE_MODULES, routine

    names = sorted(ROUTINE_MODULES)
    if only in ROUTINE_MODULES:
        names = [only]
        lines = ["parameters (give them as --param KEY=VALUE; all are optional):"]
    else:
        lines = ([f"no routine {only!r}; the routines are: {', '.join(names)}", ""] if only else []) + [
            "routines and their parameters (give them as --param KEY=VALUE; all are optional):"]
    for name in names:
        module = routine(name)
        doc = " ".join((module.__doc__ or "").strip().split("\n\n")[0].split()).replace("``", "")
        role = "engineer" if name in MOVES_ROBOT else "operator"
        lines += ["", f"{name}  (role: {role})", *textwrap.wrap(doc, 100, initial_indent="  ",
                                                                   subsequent_indent="  ")]
        schema = module.Params.model_json_schema()
        for key, prop in schema.get("properties", {}).items():
            lines += textwrap.wrap(f"{key} ({_kind(prop)}{_range(prop)}; default {_default(prop)}): "
                                   f"{prop.get('description', '')}", 100, initial_indent="    ",
                                   subsequent_indent="        ")
    return "\n".join(lines)


def _kind(prop: dict[str, Any]) -> str:
    options = prop.get("anyOf", [prop])
    kinds = []
    for o in options:
        if "enum" in o:
            kinds.append("|".join(str(v) for v in o["enum"]))
        elif o.get("type") != "null":
            kinds.append(str(o.get("type", "value")))
    return " or ".join(kinds) or "value"


def _range(prop: dict[str, Any]) -> str:
    lo = prop.get("minimum", prop.get("exclusiveMinimum"))
    hi = prop.get("maximum", prop.get("exclusiveMaximum"))
    if lo is None and hi is None:
        return ""
    left = "[" if "minimum" in prop else "("
    right = "]" if "maximum" in prop else ")"
    return f", {left}{'' if lo is None else f'{lo:g}'}..{'' if hi is None else f'{hi:g}'}{right}"


def _default(prop: dict[str, Any]) -> str:
    if "x-default" in prop:  # a parameter whose absence is not "from the config" says what it means
        return str(prop["x-default"])
    if "default" not in prop or prop["default"] is None:
        return "from the config"
    return json.dumps(prop["default"])


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser("job", help="run and follow routines on a running service")
    jsub = p.add_subparsers(dest="job_command", metavar="ACTION", required=True)
    r = jsub.add_parser("run", help="start a routine (intrinsics-capture, handeye-capture, jog-to-mark, verify)",
                        add_help=False, formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=textwrap.fill("Start a routine on a running `cellctl serve` and print its "
                                                  "job as JSON. The routines and their parameters follow "
                                                  "(the service lists them too: GET /routines).", 100))
    r.add_argument("-h", "--help", action=_HelpWithParams)
    r.add_argument("name", help="the routine: intrinsics-capture, handeye-capture, jog-to-mark or verify")
    r.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="routine parameter (JSON value or plain string); repeatable, e.g. --param views=14")
    r.add_argument("--follow", action="store_true",
                   help="show progress on stderr until the job ends (and ask before each operator step); exits 0 when "
                        "it succeeded with an ok verdict (or none), 1 when it failed, was cancelled or stopped, 3 "
                        "when it succeeded but its verdict is NOT OK (the result is stored, not activated)")
    _service_args(r)
    r.add_argument("--out", dest="out_json", help="also write the final job JSON to this file")
    r.set_defaults(func=run)
    s = jsub.add_parser("status", help="print a job")
    s.add_argument("job_id", help="the job's id (the 'id' of the job run answer)")
    _service_args(s)
    s.set_defaults(func=status)
    ls = jsub.add_parser("list", help="print the service's jobs, newest first (running and ended), as a table")
    ls.add_argument("--json", action="store_true", help="print them as a JSON list instead (every field)")
    _service_args(ls)
    ls.set_defaults(func=list_jobs)
    c = jsub.add_parser("cancel", help="cancel a running job: its routine stops the robot and stores nothing")
    c.add_argument("job_id", help="the job's id (from `cellctl job list` or the job run answer)")
    _service_args(c)
    c.set_defaults(func=cancel)


def _service_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", default=os.environ.get("CELLCTL_URL", "http://127.0.0.1:8080"), help=URL_HELP)
    p.add_argument("--token", default=os.environ.get("CELLCTL_TOKEN"), help=TOKEN_HELP)


def _token(args: argparse.Namespace) -> str:
    """The token for the service at ``args.url``: ``--token``/``$CELLCTL_TOKEN``, else the session-token
    file of *that* service's cell (its ``cell_id`` from ``GET /health``, which needs no token)."""
    if args.token:
        return str(args.token)
    import httpx

    try:
        cell_id = httpx.get(f"{args.url.rstrip('/')}/health", timeout=5.0).json()["cell_id"]
    except (httpx.HTTPError, ValueError, KeyError, TypeError) as exc:
        raise CommandError(f"cannot reach the service at {args.url} ({exc}) to find its session token; is "
                           "`cellctl serve` running there? (or give --token)") from None
    path = data_dir() / f"{cell_id}.session-token"
    if not path.is_file():
        raise CommandError(f"no token for the service at {args.url} (cell {cell_id!r}): give --token or set "
                           f"CELLCTL_TOKEN (no session-token file {path}; make a token with `cellctl token add`)")
    args.token_file = path  # a 401 then names the file (an earlier run's token, another data dir)
    return path.read_text().strip()


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


def _check(r: Any, token_file: Any = None) -> dict[str, Any]:
    if r.status_code >= 400:
        try:
            err = r.json().get("error", {})
            msg = f"{err.get('code')}: {err.get('message')}"
        except ValueError:
            msg = r.text[:200]
        if r.status_code == 401 and token_file is not None:
            msg += f"; the token came from {token_file}: is it from an earlier run? give --token"
        raise CommandError(f"the service answered {r.status_code} ({msg})")
    body: dict[str, Any] = r.json()
    return body


def run(args: argparse.Namespace) -> dict[str, Any]:
    import httpx

    try:
        with _client(args) as http:
            job = _check(http.post(f"/routines/{args.name}", json=_params(args.param)),
                         getattr(args, "token_file", None))
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
    if final.get("verdict_ok") is False:  # done, but the result did not pass: exit 3 (docs/cli.md)
        emit(final, args.out_json)
        raise CommandError(f"job {final['id']} ({final['name']}) {final['message']}", exit_code=VERDICT_NOT_OK_EXIT)
    return final


class Progress:
    """Progress on stderr. On a terminal: each new message on a line of its own (never cut), and a
    bar below it redrawn in place. Elsewhere (a log file, a pipe): one plain line per message, no
    carriage returns or escape codes."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = ""
        self._bar_shown = False

    def update(self, progress: float, message: str) -> None:
        pct = f"{progress * 100:5.1f}%"
        if not self.tty:
            self.stream.write(f"[{pct}] {message}\n")
        else:
            if message != self._last:
                self._clear()
                self.stream.write(message + "\n")
            n = int(max(0.0, min(1.0, progress)) * 30)
            self.stream.write(f"\r[{'#' * n}{'.' * (30 - n)}] {pct}")
            self._bar_shown = True
        self._last = message
        self.stream.flush()

    def line(self, text: str) -> None:
        """A line of its own (a question, the final state)."""
        self._clear()
        self.stream.write(text + "\n")
        self.stream.flush()

    def ask(self, text: str) -> None:
        self._clear()
        self.stream.write(text)
        self.stream.flush()

    def _clear(self) -> None:
        if self.tty and self._bar_shown:
            self.stream.write("\r\033[K")
            self._bar_shown = False


def _follow(http: Any, job_id: str, progress: Progress | None = None) -> None:
    out = progress or Progress()
    event = ""
    with http.stream("GET", f"/jobs/{job_id}/events", timeout=None) as stream:
        for line in stream.iter_lines():
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                data = json.loads(line[6:])
                if event == "progress":
                    out.update(float(data.get("progress", 0.0)), str(data.get("message", "")))
                elif event == "input_needed":
                    out.ask(f"{data.get('instruction', 'input needed')} — press Enter to record ")
                    if sys.stdin.readline() == "":
                        raise CommandError("no terminal input to record with; cancel the job or record over HTTP")
                    _check(http.post(f"/jobs/{job_id}/record"))
                elif event == "state":
                    shown = str(data.get("message") or "")
                    error = f" ({data['error']})" if data.get("error") and str(data["error"]) not in shown else ""
                    out.line(f"{data.get('state')}: {data.get('message')}{error}")
                    return


def _call(args: argparse.Namespace, method: str, path: str) -> Any:
    import httpx

    try:
        with _client(args) as http:
            r = http.request(method, path)
            if r.status_code < 400 and isinstance(r.json(), list):
                return r.json()
            return _check(r, getattr(args, "token_file", None))
    except httpx.HTTPError as exc:
        raise CommandError(f"cannot reach the service at {args.url} ({exc}); is `cellctl serve` running?") from None


def status(args: argparse.Namespace) -> dict[str, Any]:
    job: dict[str, Any] = _call(args, "GET", f"/jobs/{args.job_id}")
    return job


def list_jobs(args: argparse.Namespace) -> list[dict[str, Any]] | None:
    """The jobs as a table on stdout (one line each), or with ``--json`` the service's JSON list."""
    jobs: list[dict[str, Any]] = _call(args, "GET", "/jobs")
    if args.json:
        return jobs
    sys.stdout.write(jobs_table(jobs))
    return None


def jobs_table(jobs: list[dict[str, Any]]) -> str:
    """One line per job: id, routine, state, progress, verdict, who started it, when, its message."""
    import time

    head = ("ID", "ROUTINE", "STATE", "PROGRESS", "VERDICT", "BY", "STARTED", "MESSAGE")
    rows = [head]
    for j in jobs:
        verdict = "-" if j.get("verdict_ok") is None else ("ok" if j["verdict_ok"] else "NOT OK")
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(j["created_s"])) if j.get("created_s") else "-"
        message = " ".join(str(j.get("error") or j.get("message") or "").split())
        rows.append((str(j["id"]), str(j["name"]), str(j["state"]), f"{100 * float(j.get('progress') or 0):.0f}%",
                     verdict, str(j.get("started_by") or "-"), started,
                     message if len(message) <= 60 else message[:59] + "…"))
    if not jobs:
        return "no jobs on this service (start one with `cellctl job run NAME`)\n"
    widths = [max(len(r[i]) for r in rows) for i in range(len(head) - 1)]
    return "".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=False)) + "  " + r[-1] + "\n"
                   for r in rows)


def cancel(args: argparse.Namespace) -> dict[str, Any]:
    job: dict[str, Any] = _call(args, "DELETE", f"/jobs/{args.job_id}")
    return job
