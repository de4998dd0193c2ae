"""pydantic validation errors as one line a person can act on: ``key.path: message; ...``.

Used wherever cellctl refuses input that pydantic checked: ``cell.yaml``, routine parameters,
request bodies. Unknown keys read "unknown key" and, when the model is given, list the keys that
are accepted there; (unless ``with_input`` is off) the offending value is quoted, shortened, so the
user sees what was wrong without searching for it.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from pydantic import BaseModel, ValidationError

MAX_INPUT_CHARS = 60


def format_validation_errors(errors: ValidationError | Iterable[Mapping[str, Any]], prefix: str = "",
                             with_input: bool = True, model: Any = None, model_loc: int = 0) -> str:
    """The errors (a ``ValidationError`` or its ``errors()``, e.g. FastAPI's) joined by ``"; "``.

    Each reads ``loc: message``, ``loc`` dotted and prefixed with ``prefix`` (``(top level)`` when
    empty); with ``with_input`` the rejected value follows as ``(got ...)`` except for unknown and
    missing keys. ``model`` (the validated type; its fields start after the first ``model_loc``
    parts of each loc, e.g. 1 for FastAPI's ``body``): an unknown key's message lists the keys
    accepted where it was found.
    """
    items = errors.errors() if isinstance(errors, ValidationError) else errors
    parts = []
    for err in items:
        loc = ".".join(str(x) for x in err.get("loc", ()))
        if prefix:
            loc = f"{prefix}.{loc}" if loc else prefix
        kind = err.get("type", "")
        msg = "unknown key" if kind == "extra_forbidden" else str(err.get("msg", "invalid"))
        if kind == "extra_forbidden" and model is not None:
            keys = accepted_keys(model, tuple(err.get("loc", ()))[model_loc:-1])
            if keys:
                msg += f" (accepted: {', '.join(keys)})"
        hint = unit_hint(tuple(err.get("loc", ())), kind, err.get("input"))
        if hint:
            msg += hint
        if with_input and kind not in ("extra_forbidden", "missing") and "input" in err:
            shown = repr(err["input"])
            if len(shown) > MAX_INPUT_CHARS:
                shown = shown[: MAX_INPUT_CHARS - 3] + "..."
            msg += f" (got {shown})"
        parts.append(f"{loc or '(top level)'}: {msg}")
    return "; ".join(parts)


_RANGE_ERRORS = frozenset({"less_than", "less_than_equal", "greater_than", "greater_than_equal"})


def unit_hint(loc: Sequence[Any], kind: str, value: Any) -> str:
    """For a number out of range on a field in metres (``*_m``, or x, y, z of a UR pose ``*_ur``): a hint
    that the unit is metres (``400`` for ``x_m`` reads as 400 m; 0.4 m was likely meant)."""
    if kind not in _RANGE_ERRORS or isinstance(value, bool) or not isinstance(value, int | float) or not loc:
        return ""
    last = loc[-1]
    metres = isinstance(last, str) and (last.endswith("_m") or last == "m")
    if not metres and isinstance(last, int) and len(loc) > 1 and isinstance(loc[-2], str):
        metres = loc[-2].endswith("_ur") and 0 <= last < 3  # a UR pose [x_m, y_m, z_m, rx, ry, rz]
    if not metres:
        return ""
    return f" — the unit is metres: {value:g} m is {value * 1e3:g} mm; was {value / 1e3:g} m meant?"


def accepted_keys(model: Any, path: Sequence[str | int]) -> list[str] | None:
    """The keys the object at ``path`` (a validation error's loc) inside ``model`` accepts, in the
    model's order; None when no pydantic model is found there."""
    t: Any = model
    for part in path:
        t = _step(t, part)
        if t is None:
            return None
    found = _models(t)
    if len(found) != 1:
        return None
    return [f.alias or name for name, f in found[0].model_fields.items()]


def _members(t: Any) -> list[Any]:
    """``t`` without ``Annotated``/``Optional``/unions: the types it may be."""
    origin = typing.get_origin(t)
    if origin is typing.Annotated:
        return _members(typing.get_args(t)[0])
    if origin is typing.Union or origin is types.UnionType:
        return [m for a in typing.get_args(t) for m in _members(a) if m is not type(None)]
    return [t]


def _models(t: Any) -> list[type[BaseModel]]:
    return [m for m in _members(t) if isinstance(m, type) and issubclass(m, BaseModel)]


def _step(t: Any, part: str | int) -> Any:
    """The type one loc part further in (a field of a model, an item of a list or dict, a union member)."""
    for m in _members(t):
        if isinstance(m, type) and issubclass(m, BaseModel):
            if isinstance(part, str) and part in m.model_fields:
                return m.model_fields[part].annotation
            if part == m.__name__ or part in _tags(m):  # pydantic names the union member it tried
                return m
        origin = typing.get_origin(m)
        args = typing.get_args(m)
        if origin in (list, tuple, Sequence) and isinstance(part, int) and args:
            return args[0]
        if origin in (dict, Mapping) and isinstance(part, str) and len(args) == 2:
            return args[1]
    return None


def _tags(m: type[BaseModel]) -> set[Any]:
    """The values of ``m``'s ``Literal`` fields: a discriminated union's loc names its member by them."""
    return {v for f in m.model_fields.values() if typing.get_origin(f.annotation) is typing.Literal
            for v in typing.get_args(f.annotation)}
