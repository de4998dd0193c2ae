"""The house's import contracts (docs/packages.md), checked on every import statement of the product.

- ``cellctl`` → ``drivers``, ``calibration``, ``vision``: nothing in those three imports ``cellctl``;
- ``calibration`` and ``vision`` import no driver; ``vision`` imports no ``calibration``;
- the product never imports ``tests`` or ``bench`` (test support lives in ``tests/support``);
- ``cellctl.api`` and ``cellctl.cli`` do not import each other, except the one door ``cellctl serve``
  (``cellctl.cli.serve`` builds the app from ``cellctl.api.app``);
- from outside a package of calibration (``calibration.handeye``, ...) or of the virtual camera's
  imaging (``drivers.sim.imaging``), product code imports the package's public ``__init__``, never
  its private modules;
- the top of ``calibration`` holds only the shared modules: geometry, camera models, targets, the
  observations, the verdict.

Every import counts: module level, inside functions (lazy imports), and ``importlib.import_module``
with a literal name. An AST walk, no import-linter: the rules are few and the walk is 50 lines.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

from tests.conftest import REPO

PRODUCT = ("cellctl", "drivers", "calibration", "vision")
FACADES = ("calibration.pose", "calibration.intrinsics", "calibration.handeye", "calibration.npoint",
           "calibration.detect", "calibration.report", "calibration.io", "calibration.synthetic",
           "calibration.measure", "drivers.sim.imaging")
SERVICE_FACADES = ("cellctl.pick", "cellctl.store", "cellctl.production", "cellctl.plc", "cellctl.routines",
                   "cellctl.api", "cellctl.cli", "drivers.camera", "drivers.robot", "drivers.io")
"""The service's packages: each ``__init__`` is curated (an explicit ``__all__`` whose every name resolves).
Unlike calibration's facades, cellctl's own modules may still import these packages' modules directly (the
rooms are being moved in parallel; docs/packages.md says what lives where)."""
CALIBRATION_TOP = {"__init__", "geometry", "camera_model", "splined", "targets", "observations", "verdict"}
"""The shared modules at calibration's top (splined: the splined lens model's B-spline, part of camera_model)."""
ALLOWED = {("cellctl.cli.serve", "cellctl.api.app")}
"""Edges that a rule would refuse but the design needs: ``cellctl serve`` starts the REST app."""


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path, root: Path) -> Iterator[tuple[str, int]]:
    """Every module ``path`` imports (``from a import b`` yields ``a`` and ``a.b``), with its line."""
    tree = ast.parse(path.read_text(), str(path))
    me = module_name(path, root)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            yield base, node.lineno
            for alias in node.names:
                yield f"{base}.{alias.name}", node.lineno
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            yield node.args[0].value, node.lineno


def within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def rule_broken(importer: str, imported: str) -> str | None:
    """The contract ``importer → imported`` breaks, or None."""
    top, target = importer.split(".")[0], imported.split(".")[0]
    if any(importer == a and within(imported, b) for a, b in ALLOWED):
        return None
    if top in ("drivers", "calibration", "vision") and target == "cellctl":
        return f"{top} never imports cellctl (cellctl → drivers, calibration, vision)"
    if top in ("calibration", "vision") and target == "drivers":
        return f"{top} imports no driver (it works on arrays and files)"
    if top == "vision" and target == "calibration":
        return "vision imports no calibration"
    if target in ("tests", "bench"):
        return f"the product never imports {target} (test and bench support: tests/support)"
    for a, b in (("cellctl.api", "cellctl.cli"), ("cellctl.cli", "cellctl.api")):
        if within(importer, a) and within(imported, b):
            return f"{a} does not import {b} (shared pieces go to a neutral cellctl module)"
    for facade in FACADES:
        if within(imported, facade) and imported.count(".") > facade.count(".") and not within(importer, facade):
            private = imported[: len(facade)] + "." + imported[len(facade) + 1:].split(".")[0]
            if (REPO / (private.replace(".", "/") + ".py")).is_file() or (REPO / private.replace(".", "/")).is_dir():
                return f"import {facade}'s public interface (from {facade} import ...), not {private}"
    return None


def violations(root: Path) -> list[str]:
    found = []
    for package in PRODUCT:
        for path in sorted((root / package).rglob("*.py")):
            importer = module_name(path, root)
            seen: set[int] = set()
            for imported, line in imports(path, root):
                why = rule_broken(importer, imported)
                if why and line not in seen:  # one line per import statement
                    seen.add(line)
                    found.append(f"{path.relative_to(root)}:{line}: imports {imported}: {why}")
    return found


def test_the_product_keeps_the_import_contracts() -> None:
    found = violations(REPO)
    assert not found, "\n".join(found)


def test_calibration_top_holds_only_the_shared_modules() -> None:
    loose = {p.stem for p in (REPO / "calibration").glob("*.py")} - CALIBRATION_TOP
    assert not loose, f"calibration/{sorted(loose)}: put each in the package of its job (docs/packages.md)"


def test_each_facade_exists_with_a_public_interface() -> None:
    for facade in FACADES:
        init = REPO / facade.replace(".", "/") / "__init__.py"
        assert "__all__" in init.read_text(), f"{init.relative_to(REPO)} lists its public names in __all__"


def test_each_service_package_has_a_curated_interface() -> None:
    import importlib

    for facade in SERVICE_FACADES:
        init = REPO / facade.replace(".", "/") / "__init__.py"
        assert "__all__" in init.read_text(), f"{init.relative_to(REPO)} lists its public names in __all__"
        package = importlib.import_module(facade)
        names = list(package.__all__)
        assert names and len(set(names)) == len(names), f"{facade}.__all__ is empty or repeats a name"
        missing = [n for n in names if getattr(package, n, None) is None]
        assert not missing, f"{facade}.__all__ names what it does not provide: {missing}"


def test_the_package_map_names_files_that_exist() -> None:
    """docs/packages.md answers "where is ..." with paths; each must be there."""
    text = (REPO / "docs" / "packages.md").read_text()
    paths = {p for p in re.findall(r"`([a-z_]+/[\w/.]*)`", text)}
    assert len(paths) > 30
    missing = sorted(p for p in paths if not (REPO / p).exists())
    assert not missing, f"docs/packages.md names paths that do not exist: {missing}"


def test_the_rules_catch_what_they_are_for(tmp_path: Path) -> None:
    files = {
        "calibration/bad.py": "from cellctl.config import load_config\nimport drivers.sim.imaging\n",
        "vision/bad.py": "def f():\n    from calibration import geometry\n",
        "drivers/sim/bad.py": "import importlib\nimportlib.import_module('cellctl.cell')\n",
        "cellctl/cli/bad.py": "from cellctl.api.routes import map\n",
        "cellctl/api/bad.py": "from ..cli import output\n",
        "cellctl/bad.py": "from calibration.handeye.solve import calibrate_handeye\nfrom tests.support import served\n",
        "cellctl/good.py": ("from calibration.handeye import calibrate_handeye\n"
                            "from drivers.sim.imaging import render\n"),
        "cellctl/cli/serve.py": "from cellctl.api.app import create_app\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    found = violations(tmp_path)
    assert all("good.py" not in v and "serve.py" not in v for v in found)
    for where, what in [("calibration/bad.py:1", "cellctl"), ("calibration/bad.py:2", "no driver"),
                        ("vision/bad.py:2", "no calibration"), ("drivers/sim/bad.py:2", "never imports cellctl"),
                        ("cellctl/cli/bad.py:1", "cellctl.cli does not import cellctl.api"),
                        ("cellctl/api/bad.py:1", "cellctl.api does not import cellctl.cli"),
                        ("cellctl/bad.py:1", "calibration.handeye.solve"), ("cellctl/bad.py:2", "never imports tests")]:
        assert any(v.startswith(where) and what in v for v in found), (where, what, found)
