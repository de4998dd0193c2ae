"""docs/routines/<name>.md documents every routine's every parameter with its true default, and
docs/routines.md links every routine's page."""

from __future__ import annotations

import re

from cellctl.cli.job import _default
from cellctl.routines import ROUTINE_MODULES, routine
from tests.conftest import REPO


def test_every_parameter_is_documented_with_its_default() -> None:
    index = (REPO / "docs" / "routines.md").read_text()
    pages = {p.stem: p.read_text() for p in (REPO / "docs" / "routines").glob("*.md")}
    assert set(pages) == set(ROUTINE_MODULES)
    sections = {}
    for name, text in pages.items():
        assert f"(routines/{name}.md)" in index, f"docs/routines.md does not link {name}"
        assert text.startswith(f"# Routine: {name}\n")
        sections[name] = text
    for name in ROUTINE_MODULES:
        props = routine(name).Params.model_json_schema()["properties"]
        rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([a-z_]+)` \|.*$", sections[name], re.M)}
        assert set(rows) == set(props), name
        for key, prop in props.items():
            cells = [c.strip() for c in rows[key].strip("|").split("|")]
            assert cells[2] == _default(prop), (name, key, cells)
            assert prop["description"] in cells[3], (name, key)
