"""cellctl is Apache-2.0 (LICENSE, pyproject); docs/licences.md lists every runtime dependency with its
licence as pip's metadata gives it, and each is one an Apache-2.0 project may depend on."""

from __future__ import annotations

import re
import tomllib

from tests.conftest import REPO
from tests.docs.licence_check import kind, licence_text, runtime_closure


def test_the_project_is_apache_2() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["license"] == "Apache-2.0" and project["license-files"] == ["LICENSE"]
    text = (REPO / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text and "END OF TERMS AND CONDITIONS" in text


def test_every_runtime_dependency_is_listed_with_a_compatible_licence() -> None:
    doc = (REPO / "docs" / "licences.md").read_text()
    rows = {m.group(1).lower().replace("_", "-").replace(".", "-"): m.group(2)
            for m in re.finditer(r"^\| `([^`]+)` \| [^|]* \| ([a-z ]+) \|", doc, re.MULTILINE)}
    closure = runtime_closure()
    assert len(closure) > 20
    for key, dist in sorted(closure.items()):
        if key == "cellctl":
            continue
        found = kind(licence_text(dist))
        assert found != "unknown", f"{key}: licence {licence_text(dist)!r} not recognised; check it and classify it"
        assert key in rows, f"{key} ({licence_text(dist)}) is not listed in docs/licences.md"
        assert rows[key] == found, f"{key}: docs/licences.md says {rows[key]}, the metadata {found}"
        if found == "strong copyleft":
            assert f"`{dist.metadata['Name']}`" in doc.split("## Strong copyleft", 1)[-1], key
