"""A request body's JSON, parsed once, bounded in shape, and never parsed or validated on the event loop when large.

:func:`inspect_body` (run by the edge, after the caller's token and role are checked) parses a JSON
body with Python's ``json`` and refuses, with 422 naming the field (``body.recipe.models.0.teach.roi.2``):

- a number that is not a finite double: ``NaN``, ``Infinity``, ``1e999`` (Python's ``json`` takes them);
- a number literal longer than :data:`MAX_NUMBER_CHARS` characters (a 400-digit integer or a float
  written out in 400 digits is no measurement; it would become a huge int or an infinity);
- nesting deeper than :data:`MAX_DEPTH`, or more than :data:`MAX_VALUES` values in the body.

The parse calls back into Python for every number, so a large body parsed in a worker thread hands
the interpreter lock back to the event loop between numbers (a plain ``json.loads`` holds it for
the whole body). The parsed document goes to the route in the scope (:data:`PARSED_KEY`): FastAPI
reads it from there (:class:`EdgeRoute`) instead of parsing the body again, and a large body is
validated against the route's model in the body pool too (``cellctl.api.pools``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import Response

from cellctl.api.pools import Pools, run_blocking

MAX_NUMBER_CHARS = 40
"""Longest JSON number literal (a double needs at most 24 characters: ``-2.2250738585072014e-308``)."""
MAX_DEPTH = 32
"""Deepest nesting of arrays and objects (a recipe's part model is 7 deep)."""
MAX_VALUES = 500_000
"""Most values (numbers, strings, arrays, objects) in one body; a taught part model has tens of thousands."""

PARSED_KEY = "cellctl.json"
"""The scope key of the parsed body (:class:`Parsed`)."""


@dataclass(frozen=True)
class Parsed:
    """A body the edge parsed: the document, or the ``json`` error it raised; ``large``: parsed off the loop."""

    doc: Any = None
    error: json.JSONDecodeError | None = None
    large: bool = False


class _Refused:
    """A number the parse refused (found again by :func:`_path_of` to name its field)."""

    def __init__(self, literal: str, why: str) -> None:
        self.literal = literal
        self.why = why


def inspect_body(body: bytes, large: bool = False) -> tuple[Parsed | None, str | None]:
    """``(parsed, None)`` for a body fit to route (``parsed`` None when it is not JSON text at all),
    or ``(None, problem)`` naming the field and what to send instead."""
    separators = body.count(b",")
    if separators >= MAX_VALUES:
        return None, (f"the body holds {separators + 1} or more values, the limit is {MAX_VALUES}: "
                      "send less per request")
    refused: list[_Refused] = []

    def number(literal: str, kind: Callable[[str], Any]) -> Any:
        if len(literal) > MAX_NUMBER_CHARS:
            bad = _Refused(f"{literal[:12]}...({len(literal)} characters)",
                           f"is a number of {len(literal)} characters; JSON numbers here have at most "
                           f"{MAX_NUMBER_CHARS} (a double needs 24): send a value in the field's range")
            refused.append(bad)
            return bad
        value = kind(literal)
        if isinstance(value, float) and not math.isfinite(value):
            return _non_finite(literal, refused)
        return value

    try:
        doc = json.loads(body, parse_float=lambda s: number(s, float), parse_int=lambda s: number(s, int),
                         parse_constant=lambda s: _non_finite(s, refused))
    except json.JSONDecodeError as exc:
        return Parsed(error=exc, large=large), None
    except UnicodeDecodeError:
        return None, None  # not text: the route says what it takes
    except RecursionError:
        return None, f"the body is nested more than {MAX_DEPTH} levels deep: send a flatter document"
    if refused:
        path = _path_of(doc, refused[0])
        return None, f"{path}: {refused[0].literal} {refused[0].why}"
    problem = _shape_problem(doc, body)
    return (None, problem) if problem else (Parsed(doc, large=large), None)


def _non_finite(literal: str, refused: list[_Refused]) -> _Refused:
    bad = _Refused(literal, "is not a finite number; JSON numbers here must be finite (no NaN, Infinity or values "
                            "beyond +-1.8e308): send a finite value in the field's range")
    refused.append(bad)
    return bad


def _shape_problem(doc: Any, body: bytes) -> str | None:
    """Too deep or too many values (counted level by level, only when the brackets allow either)."""
    if body.count(b"[") + body.count(b"{") <= MAX_DEPTH and body.count(b",") < MAX_VALUES:
        return None
    level, depth, values = [doc], 0, 1
    while level:
        depth += 1
        if depth > MAX_DEPTH:
            return f"the body is nested more than {MAX_DEPTH} levels deep: send a flatter document"
        below: list[Any] = []
        for v in level:
            items = v.values() if isinstance(v, dict) else v
            values += len(items)
            below.extend(x for x in items if isinstance(x, list | dict))
        if values > MAX_VALUES:
            return f"the body holds more than {MAX_VALUES} values: send less per request"
        level = below
    return None


def _path_of(doc: Any, target: _Refused) -> str:
    """The dotted path (``body.a.0.b``) of ``target`` in ``doc``."""
    stack: list[tuple[Any, tuple[str, ...]]] = [(doc, ("body",))]
    while stack:
        value, path = stack.pop()
        if value is target:
            return ".".join(path)
        if isinstance(value, dict):
            stack.extend((v, (*path, str(k))) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((v, (*path, str(i))) for i, v in enumerate(value))
    return "body"


class _EdgeRequest(Request):
    """A request whose ``json()`` is the edge's parse (no second parse of the body)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            parsed = self.scope.get(PARSED_KEY)
            if not isinstance(parsed, Parsed):
                return await super().json()
            if parsed.error is not None:
                raise parsed.error
            self._json = parsed.doc
        return self._json


class EdgeRoute(APIRoute):
    """The routes' class: FastAPI takes the body the edge parsed, and a large body is validated
    against the route's model in the body pool (FastAPI then takes the validated model as it is)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        body_field = self.body_field
        single_body = body_field is not None and len(self.dependant.body_params) == 1

        async def edge_handler(request: Request) -> Response:
            parsed = request.scope.get(PARSED_KEY)
            if (isinstance(parsed, Parsed) and parsed.large and parsed.error is None and single_body
                    and body_field is not None):
                pools: Pools | None = getattr(request.app.state, "pools", None)
                value, errors = await run_blocking(
                    lambda: body_field.validate(parsed.doc, {}, loc=("body",)),
                    pool=pools.body if pools else None)
                if errors:
                    raise RequestValidationError(errors)
                request.scope[PARSED_KEY] = Parsed(value, large=True)
            return await handler(_EdgeRequest(request.scope, request.receive))

        return edge_handler
