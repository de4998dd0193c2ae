"""Fuzzing the served API: no 5xx for any generated request, and none for hostile numbers anywhere.

Two runs against one ``cellctl serve`` of the virtual cell:

- a bounded schemathesis run over the served OpenAPI schema (its examples, coverage and fuzzing
  phases; the coverage phase sends wrong types and boundary values for every parameter);
- a deterministic sweep over every operation of the schema: each number a request can carry (a
  body field at any depth, a path or query parameter) is replaced in turn by a bool, a string, a
  400-digit integer, a float written out in 400 digits, a 400-digit fraction and the extremes of
  a double, sent as raw JSON text with an engineer's token (issue 21: such numbers gave 78 x 500).

The routines are left out (each would start a long robot job; their parameters are swept in
tests/cellctl/test_edge.py), as are production runs; a longer, unbounded schemathesis run that
includes them is ``bench/api_fuzz.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from cellctl.config import default_config_text
from tests.conftest import Served, start_served, stop_served

LEFT_OUT = ("/routines/", "/production/start", "/production/slot", "/production/gripper")
HOSTILE = ["true", "false", '"0.4"', "1" * 400, "-" + "1" * 400, "1" + "0" * 398 + ".5", "0." + "0" * 398 + "1",
           "1e300", "-1e300", "1e-300", "18446744073709551617"]
"""JSON literals put where a number belongs."""
HOSTILE_PARAMS = ["1" * 400, "-" + "1" * 400, "1" + "0" * 398 + ".5", "true", "1e300", "18446744073709551617", "-1"]
PATH_VALUES = {"robot_id": "robot0", "camera_id": "cam0", "name": "plate", "job_id": "nosuchjob"}
MARK = "@@hostile@@"


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    tmp = tmp_path_factory.mktemp("fuzz")
    data = yaml.safe_load(default_config_text())
    # Instantaneous moves: the fuzz checks every answer, not the travel of the moves it happens to make.
    data["robots"]["robot0"]["settings"]["motion_time_scale"] = 0.0
    (tmp / "cell.yaml").write_text(yaml.safe_dump(data))
    s = start_served(tmp, tmp / "cell.yaml")
    try:
        yield s
    finally:
        stop_served(s)


def test_schemathesis_finds_no_server_error(served: Served) -> None:
    st = str(Path(sys.executable).with_name("schemathesis"))
    r = subprocess.run(
        [st, "run", served.base_url + "/openapi.json", "-H", f"Authorization: Bearer {served.token}",
         "--checks", "not_a_server_error", "--max-examples", "8", "--seed", "20261123",
         "--exclude-path-regex", "^/(routines|production)/", "--request-timeout", "20", "--workers", "1",
         "--phases", "examples,coverage,fuzzing"],
        capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-6000:]
    assert "Server error" not in r.stdout


# -- hostile numbers everywhere ---------------------------------------------------------------------------

class Schemas:
    """Builds a plain instance of a schema and lists where its numbers are (``$ref``s resolved)."""

    def __init__(self, spec: dict[str, Any]) -> None:
        self.components = spec.get("components", {}).get("schemas", {})

    def resolve(self, schema: dict[str, Any]) -> dict[str, Any]:
        while "$ref" in schema:
            schema = self.components[schema["$ref"].rsplit("/", 1)[1]]
        for key in ("anyOf", "oneOf"):
            if key in schema:
                options = [o for o in schema[key] if self.resolve(o).get("type") != "null"]
                return self.resolve(options[0]) if options else {"type": "null"}
        if "allOf" in schema and len(schema["allOf"]) == 1:
            return self.resolve(schema["allOf"][0])
        return schema

    def instance(self, schema: dict[str, Any], depth: int = 0) -> Any:
        """A plain value: every property with a number (optional strings left out: ids would 404)."""
        s = self.resolve(schema)
        if "default" in s and s.get("type") not in ("object", "array"):
            return s["default"]
        if "const" in s or "enum" in s:
            return s.get("const", (s.get("enum") or [None])[0])
        kind = s.get("type")
        if kind == "object" or "properties" in s:
            required = set(s.get("required", []))
            out = {}
            for name, sub in s.get("properties", {}).items():
                if name in required or (depth < 8 and self._has_numbers(sub)):
                    out[name] = self.instance(sub, depth + 1)
            return out
        if kind == "array":
            if "prefixItems" in s:
                return [self.instance(x, depth + 1) for x in s["prefixItems"]]
            return [self.instance(s.get("items", {}), depth + 1) for _ in range(max(1, s.get("minItems", 1)))]
        if kind in ("number", "integer"):
            lo = s.get("minimum", s.get("exclusiveMinimum", 0))
            value = max(lo, min(s.get("maximum", lo + 1), 1))
            return int(value) if kind == "integer" else float(value)
        return {"boolean": False, "string": "x"}.get(str(kind))

    def _has_numbers(self, schema: dict[str, Any], seen: int = 0) -> bool:
        return seen < 12 and any(True for _ in self.numbers(schema, (), seen))

    def numbers(self, schema: dict[str, Any], path: tuple[Any, ...] = (), depth: int = 0
                ) -> Iterator[tuple[Any, ...]]:
        """Paths (keys and indices) to the numbers of an instance of ``schema``."""
        if depth > 12:
            return
        s = self.resolve(schema)
        kind = s.get("type")
        if kind in ("number", "integer"):
            yield path
        elif kind == "object" or "properties" in s:
            for name, sub in s.get("properties", {}).items():
                yield from self.numbers(sub, (*path, name), depth + 1)
        elif kind == "array":
            items = s.get("prefixItems") or [s.get("items", {})]
            for i, sub in enumerate(items):
                yield from self.numbers(sub, (*path, i), depth + 1)


def _put(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    target = doc
    for k in path[:-1]:
        target = target[k]
    target[path[-1]] = value
    return doc


def _requests(spec: dict[str, Any]) -> Iterator[tuple[str, str, str | None, str]]:
    """(method, url, JSON text or None, what was put where) for every hostile number of every operation."""
    schemas = Schemas(spec)
    for template, ops in spec["paths"].items():
        if template.startswith(LEFT_OUT):
            continue
        for method, op in ops.items():
            params = op.get("parameters", [])
            values: dict[str, str] = {p["name"]: PATH_VALUES.get(p["name"], "1") for p in params if p["in"] == "path"}
            body_schema = (op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema"))
            plain = schemas.instance(body_schema) if body_schema else None
            for p in params:
                kind = schemas.resolve(p.get("schema", {})).get("type")
                if kind not in ("integer", "number"):
                    continue
                for bad in HOSTILE_PARAMS:
                    where = {**values, p["name"]: bad} if p["in"] == "path" else values
                    url = template.format(**where) + (f"?{p['name']}={bad}" if p["in"] == "query" else "")
                    yield method, url, None if plain is None else json.dumps(plain), f"{p['name']}={bad[:20]}"
            if body_schema is None:
                continue
            url = template.format(**values)
            for path in schemas.numbers(body_schema):
                for bad in HOSTILE:
                    text = json.dumps(_put(json.loads(json.dumps(plain)), path, MARK)).replace(f'"{MARK}"', bad)
                    yield method, url, text, f"{'.'.join(map(str, path))}={bad[:20]}"


def test_hostile_numbers_in_every_operation_answer_no_server_error(served: Served) -> None:
    with httpx.Client(base_url=served.base_url, timeout=30.0,
                      headers={"Authorization": f"Bearer {served.token}", "Content-Type": "application/json"}) as http:
        spec = http.get("/openapi.json").json()
        sent, errors = 0, []
        for method, url, text, what in _requests(spec):
            try:
                r = http.request(method.upper(), url, content=None if text is None else text.encode())
            except httpx.HTTPError as exc:
                errors.append(f"{method.upper()} {url} {what}: {exc!r}")
                continue
            sent += 1
            if r.status_code >= 500 and r.status_code != 503:  # 503: a device that is not there, not a bug
                errors.append(f"{method.upper()} {url} {what}: {r.status_code} {r.text[:200]}")
            if method == "post" and url.endswith("/stop"):
                http.post(url.replace("/stop", "/resume"))
    assert sent > 500  # every operation's numbers, each with every hostile value
    assert not errors, "\n".join(errors[:20])
