"""The one lazy-import helper (``drivers.lazy.lazy_getattr``) behind the curated ``__init__``s: a name
resolves from its module on first use and is then kept, an unknown name is an ``AttributeError``, and
importing a package imports none of its modules."""

from __future__ import annotations

import subprocess
import sys
import types

import pytest

from drivers.lazy import lazy_getattr
from tests.conftest import REPO

LAZY_PACKAGES = ("cellctl.api", "cellctl.pick", "cellctl.production", "drivers.camera", "drivers.io",
                 "drivers.robot")


def test_a_name_is_imported_on_first_use_and_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    package = types.ModuleType("lazy_demo")
    monkeypatch.setitem(sys.modules, "lazy_demo", package)
    package.__getattr__ = lazy_getattr("lazy_demo", {"dumps": "json"})  # type: ignore[method-assign]
    import json

    assert package.dumps is json.dumps  # type: ignore[attr-defined]
    assert vars(package)["dumps"] is json.dumps  # kept: the next lookup does not come back
    with pytest.raises(AttributeError, match="module 'lazy_demo' has no attribute 'loads'"):
        package.loads  # type: ignore[attr-defined]  # noqa: B018


def test_importing_a_package_runs_none_of_its_modules() -> None:
    code = ("import sys\n"
            f"for p in {LAZY_PACKAGES!r}:\n"
            "    __import__(p)\n"
            f"loaded = sorted(m for m in sys.modules if any(m.startswith(p + '.') for p in {LAZY_PACKAGES!r}))\n"
            "print(loaded)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout
