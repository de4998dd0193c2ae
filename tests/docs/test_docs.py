"""docs/ is kept true: its commands exist, its routes exist, its examples parse and run, its links resolve."""

from __future__ import annotations

import argparse
import functools
import json
import re
from typing import Any

import numpy as np
import pytest
import yaml

from tests.conftest import REPO

DOCS = REPO / "docs"
PAGES = sorted(DOCS.rglob("*.md"))  # docs/*.md and the per-type pages (docs/targets/*.md)
README = REPO / "README.md"


def _fenced(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def _page(name: str) -> str:
    return (DOCS / name).read_text()


# -- the command line ---------------------------------------------------------------------------

def _shown_commands(text: str) -> list[str]:
    """``cellctl ...`` as shown: inline code spans and lines of fenced blocks (``.venv/bin/`` allowed)."""
    spans = re.findall(r"`([^`\n]+)`", text)
    lines = [ln for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S) for ln in block.splitlines()]
    found = []
    for s in spans + lines:
        m = re.match(r"\s*(?:\.venv/bin/)?(cellctl(?:\s.*)?)$", s.strip())
        if m:
            found.append(m.group(1))
    return found


def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def _options(p: argparse.ArgumentParser) -> set[str]:
    return {o for a in p._actions for o in a.option_strings}


def check_command(parser: argparse.ArgumentParser, command: str) -> list[str]:
    """What in ``command`` the parser does not know (empty when all of it exists).

    ``a|b`` in a command's place shows two commands: each must exist, and an option shown after
    them must belong to at least one (``cellctl token list|remove --config C [--name N]``).
    """
    words = command.replace("[", " ").replace("]", " ").split()[1:]
    parsers, path, problems = [parser], ["cellctl"], []
    for w in words:
        w = w.strip("'\"")
        if w.startswith("-"):
            for alt in w.split("/"):
                opt = alt.split("=")[0]
                if opt and not any(opt in _options(p) for p in parsers):
                    problems.append(f"{' '.join(path)}: no option {opt}")
            continue
        subs = _subparsers(parsers[0])
        if subs:
            names = w.split("|") if all(a in subs for a in w.split("|")) else [w]
            if names[0] not in subs:
                problems.append(f"{' '.join(path)}: no command {w!r} (has {sorted(subs)})")
                break
            parsers, path = [subs[n] for n in names], [*path, w]
    if _subparsers(parsers[0]) and words and not {"-h", "--help", "--version"} & set(words):
        problems.append(f"{' '.join(path)}: incomplete, needs one of {sorted(_subparsers(parsers[0]))}")
    return problems


def test_every_command_shown_in_the_docs_exists_in_the_parser() -> None:
    from cellctl.cli import build_parser

    parser = build_parser()
    shown = {(path.name, c) for path in [*PAGES, README] for c in _shown_commands(path.read_text())}
    assert len([c for name, c in shown if name == "cli.md"]) >= 30  # the page shows the commands
    problems = [f"{name}: `{c}`: {p}" for name, c in sorted(shown) for p in check_command(parser, c)]
    assert not problems, "\n".join(problems)


def test_the_command_check_catches_what_does_not_exist() -> None:
    from cellctl.cli import build_parser

    parser = build_parser()
    assert check_command(parser, "cellctl detect --target T.yaml IMAGE") == []
    assert check_command(parser, "cellctl token list|remove --config cell.yaml [--name N]") == []
    assert check_command(parser, "cellctl token list|purge --config cell.yaml")
    assert check_command(parser, "cellctl detect --no-such-option 3")
    assert check_command(parser, "cellctl calib nonsense --out x")
    assert check_command(parser, "cellctl calib")  # a group without its command


def test_every_command_of_the_parser_is_in_cli_md() -> None:
    from cellctl.cli import build_parser

    shown = {" ".join(c.replace("[", " ").split()[:3]) for c in _shown_commands(_page("cli.md"))}

    def leaves(p: argparse.ArgumentParser, path: list[str]) -> list[str]:
        subs = _subparsers(p)
        if not subs:
            return [" ".join(path)]
        return [leaf for name, sp in subs.items() for leaf in leaves(sp, [*path, name])]

    missing = [leaf for leaf in leaves(build_parser(), ["cellctl"])
               if not any(s == leaf or s.startswith(leaf + " ") for s in shown)]
    assert not missing, f"commands not in docs/cli.md: {missing}"


# -- the REST contract --------------------------------------------------------------------------

ROUTE = re.compile(r"\b(GET|POST|PUT|PATCH|DELETE) (/[^\s`|,)?]*)")


def _norm(path: str) -> str:
    return re.sub(r"\{[^}]*\}", "{}", path.rstrip("/") or "/")


@functools.cache
def _app() -> Any:
    """The service's app for the route checks (made once per process; they only read its routes and schema)."""
    from cellctl.api.app import create_app
    from cellctl.config import load_config

    return create_app(load_config(None))


def _openapi_routes(app: Any) -> set[tuple[str, str]]:
    return {(m.upper(), _norm(p)) for p, ops in app.openapi()["paths"].items() for m in ops}


def _routed(app: Any, method: str, url: str) -> bool:
    """Whether the app's router has a route for ``method url`` (matched as a request would be)."""
    from starlette.routing import Match

    scope = {"type": "http", "method": method, "path": url, "root_path": "", "query_string": b"", "headers": []}
    return any(route.matches(scope)[0] == Match.FULL for route in app.router.routes)


def test_every_route_in_rest_md_exists_in_the_service() -> None:
    app = _app()
    in_openapi = _openapi_routes(app)
    shown = {(m, _norm(p)) for m, p in ROUTE.findall(_page("rest.md"))}
    assert len(shown) >= 30
    # The operator page, its files, the docs and /openapi.json are served but not in the API schema:
    # ask the router (a static file name stands in for {name}).
    static = sorted(p.name for p in (REPO / "cellctl" / "static").iterdir() if p.is_file())
    missing = sorted((m, p) for m, p in shown - in_openapi if not _routed(app, m, p.replace("{}", static[0])))
    assert not missing, f"docs/rest.md names routes the service does not have: {missing}"
    assert not _routed(app, "GET", "/no/such/route") and not _routed(app, "DELETE", "/health")
    for open_route in [("GET", "/health"), ("GET", "/openapi.json"), ("GET", "/docs"), ("GET", "/")]:
        assert open_route in shown and _routed(app, *open_route)


def test_every_route_of_the_openapi_is_in_rest_md() -> None:
    in_openapi = _openapi_routes(_app())
    shown = {(m, _norm(p)) for m, p in ROUTE.findall(_page("rest.md"))}
    missing = sorted(in_openapi - shown)
    assert not missing, f"routes of /openapi.json not described in docs/rest.md: {missing}"


def test_error_codes_in_rest_md_are_the_codes_the_code_sends() -> None:
    table = _page("rest.md").split("## Errors", 1)[1].split("## Routes", 1)[0]
    codes = set(re.findall(r"`([a-z]+(?:_[a-z]+)+|[a-z]+)`", table)) - {"code", "message"}
    source = "\n".join(p.read_text() for d in ("cellctl", "drivers") for p in (REPO / d).rglob("*.py"))
    templated = {"unknown_camera", "unknown_robot"}  # f"unknown_{kind}" in cellctl/api/deps.py
    assert 'f"unknown_{kind}"' in source
    missing = sorted(c for c in codes - templated if f'"{c}"' not in source)
    assert not missing, f"docs/rest.md lists error codes that nothing sends: {missing}"


# -- formats and examples -----------------------------------------------------------------------

def test_target_examples_parse_and_their_geometry_is_as_written() -> None:
    from calibration.targets import Chessboard, CircleGrid, CirclePlate, target_from_dict

    types = ["chessboard", "charuco", "circle_plate", "circle_grid", "points3d"]
    targets = []
    for kind in types:  # one page per type, each with its one file example
        blocks = [yaml.safe_load(b) for b in _fenced(_page(f"targets/{kind}.md"), "yaml")]
        assert len(blocks) == 1, f"docs/targets/{kind}.md shows {len(blocks)} target files"
        targets.append(target_from_dict(blocks[0], f"docs/targets/{kind}.md"))
    assert [t.type for t in targets] == types
    board, plate, grid = targets[0], targets[2], targets[3]
    assert isinstance(board, Chessboard) and isinstance(plate, CirclePlate)
    for t, step_mm in ((board, 25.0), (plate, 12.5)):  # id r*cols+c at (c*step, r*step, 0)
        pts = t.points()
        r, c = np.divmod(pts.ids, t.cols)
        assert np.allclose(pts.xyz_m, np.column_stack([c, r, 0 * r]) * step_mm / 1000)
    assert isinstance(grid, CircleGrid) and grid.asymmetric
    pts = grid.points()
    r, c = np.divmod(pts.ids, grid.cols)
    assert np.allclose(pts.xyz_m[:, :2], np.column_stack([2 * c + r % 2, r]) * 0.020)
    assert np.allclose(plate.frame_inner_m(), (-0.0125, -0.0125, 7 * 0.0125, 7 * 0.0125))


def test_each_target_page_names_a_shipped_example_of_its_type() -> None:
    from calibration.targets import load_target

    for kind in ["chessboard", "charuco", "circle_plate", "circle_grid", "points3d"]:
        text = _page(f"targets/{kind}.md")
        shipped = re.findall(r"`(deploy/examples/targets/[^`]+\.yaml)`", text)
        assert len(shipped) == 1, f"docs/targets/{kind}.md names {shipped}"
        assert load_target(REPO / shipped[0]).type == kind
        assert f"(targets/{kind}.md)" in _page("targets.md"), f"docs/targets.md does not link {kind}"


def test_json_examples_are_json() -> None:
    blocks = [(p.name, b) for p in PAGES for b in _fenced(p.read_text(), "json")]
    assert len(blocks) >= 5
    for name, b in blocks:
        json.loads(b.replace("...", ""))  # an elided message is still JSON
        assert name


OWN_PAGES = ["conventions.md", "targets.md", "datasets.md", "cli.md", "rest.md", "field-notes.md", "testing.md"]


@pytest.mark.parametrize("page", [p for p in OWN_PAGES if "```python" in (DOCS / p).read_text()])
def test_python_examples_run(page: str) -> None:
    for block in _fenced(_page(page), "python"):
        exec(compile(block, f"docs/{page}", "exec"), {})  # noqa: S102 - our own documentation


def _anchors(text: str) -> set[str]:
    out = set()
    for title in re.findall(r"^#+ (.+)$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        out.add(slug)
    return out


def test_links_between_pages_resolve() -> None:
    for page in [*PAGES, README]:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+://", target):
                continue
            file, _, anchor = target.partition("#")
            dest = (page.parent / file).resolve() if file else page
            assert dest.exists(), f"{page.name}: link to {target}: no such file"
            if anchor and dest.suffix == ".md":
                assert anchor in _anchors(dest.read_text()), f"{page.name}: link to {target}: no such heading"


def test_the_index_links_every_page() -> None:
    index = _page("README.md")
    for page in PAGES:
        if page.name != "README.md" and page.parent == DOCS:  # sub-pages are linked from their own index
            assert f"]({page.name}" in index, f"docs/README.md does not link {page.name}"
