"""pydantic validation errors as one line a person can act on: ``key.path: message; ...``.

Used wherever cellctl refuses input that pydantic checked: ``cell.yaml``, routine parameters,
request bodies. Unknown keys read "unknown key", and (unless ``with_input`` is off) the offending
value is quoted, shortened, so the user sees what was wrong without searching for it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import ValidationError

MAX_INPUT_CHARS = 60


def format_validation_errors(errors: ValidationError | Iterable[Mapping[str, Any]], prefix: str = "",
                             with_input: bool = True) -> str:
    """The errors (a ``ValidationError`` or its ``errors()``, e.g. FastAPI's) joined by ``"; "``.

    Each reads ``loc: message``, ``loc`` dotted and prefixed with ``prefix`` (``(top level)`` when
    empty); with ``with_input`` the rejected value follows as ``(got ...)`` except for unknown and
    missing keys.
    """
    items = errors.errors() if isinstance(errors, ValidationError) else errors
    parts = []
    for err in items:
        loc = ".".join(str(x) for x in err.get("loc", ()))
        if prefix:
            loc = f"{prefix}.{loc}" if loc else prefix
        kind = err.get("type", "")
        msg = "unknown key" if kind == "extra_forbidden" else str(err.get("msg", "invalid"))
        if with_input and kind not in ("extra_forbidden", "missing") and "input" in err:
            shown = repr(err["input"])
            if len(shown) > MAX_INPUT_CHARS:
                shown = shown[: MAX_INPUT_CHARS - 3] + "..."
            msg += f" (got {shown})"
        parts.append(f"{loc or '(top level)'}: {msg}")
    return "; ".join(parts)
