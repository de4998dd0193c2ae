"""One error root per library: every exception class of ``calibration`` and ``vision`` derives from it.

The REST API maps these roots (and the drivers' ``DriverError``) to a 4xx; any other exception is
a bug (a 500 with a request id). A new error class outside its root would silently become a 500.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import json
import pkgutil
import re
import tempfile
from pathlib import Path

import pytest

import calibration
import vision
from calibration import CalibrationError
from vision.errors import VisionError


def _exception_classes(package: object) -> list[type[BaseException]]:
    """The exception classes defined (not just imported) in ``package`` and its modules."""
    name = package.__name__  # type: ignore[attr-defined]
    modules = [package] + [importlib.import_module(m.name) for m in
                           pkgutil.walk_packages(package.__path__, name + ".")  # type: ignore[attr-defined]
                           if not m.name.endswith("__main__")]
    found = {obj for module in modules for _, obj in inspect.getmembers(module, inspect.isclass)
             if issubclass(obj, BaseException) and obj.__module__.split(".")[0] == name}
    return sorted(found, key=lambda c: f"{c.__module__}.{c.__qualname__}")


@pytest.mark.parametrize(("package", "root"), [(calibration, CalibrationError), (vision, VisionError)])
def test_every_exception_class_derives_from_the_library_root(package: object, root: type) -> None:
    classes = _exception_classes(package)
    assert root in classes and len(classes) >= (20 if package is calibration else 4)
    strays = [f"{c.__module__}.{c.__qualname__}" for c in classes if not issubclass(c, root)]
    assert not strays, f"derive these from {root.__name__}: {strays}"
    # Still ValueErrors: callers that catch bad input as a ValueError keep working.
    assert all(issubclass(c, ValueError) for c in classes)


@pytest.mark.parametrize(("package_name", "root_path"), [("drivers", "drivers.errors.DriverError"),
                                                         ("cellctl", "cellctl.errors.CellctlError")])
def test_every_exception_class_of_the_service_derives_from_its_package_root(package_name: str,
                                                                             root_path: str) -> None:
    """``DriverError`` roots every driver error (the virtual cell's input errors through
    ``DriverInputError``), ``CellctlError`` every cellctl error: ``cellctl.api.errors`` maps the roots."""
    from cellctl.api.errors import OWN_ERRORS

    package = importlib.import_module(package_name)
    module_name, _, class_name = root_path.rpartition(".")
    root = getattr(importlib.import_module(module_name), class_name)
    classes = _exception_classes(package)
    assert root in classes and len(classes) >= (12 if package_name == "drivers" else 20)
    strays = [f"{c.__module__}.{c.__qualname__}" for c in classes if not issubclass(c, root)]
    assert not strays, f"derive these from {root.__name__}: {strays}"
    assert root in OWN_ERRORS


FLAG = re.compile(r"(?<![\w-])--[A-Za-z][A-Za-z0-9]*(-[A-Za-z0-9]+)*")
TWO_DASHES_POSSIBLE = re.compile(r"--|\\|-[\"']")
"""What the text of a module holds if any of its string constants holds two dashes in a row: the two side by
side in one literal, an escape (``\x2d``, a line continuation), or a literal that ends in a dash (concatenated
with the next). A module with none of them cannot name a flag and is not parsed (about 1 in 4 is)."""


def _message_strings(path: Path) -> list[tuple[int, str]]:
    """The string literals of a module (f-string parts included) other than docstrings and bare string
    statements: what can end up in a message."""
    tree = ast.parse(path.read_text(), str(path))
    docs = {id(node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)}
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs]


@pytest.mark.parametrize("package", ["calibration", "vision"])
def test_no_library_message_names_a_command_line_flag(package: str) -> None:
    """Library messages say what is wrong in the library's words; the CLI adds its flags (cellctl/hints.py).
    A package's own ``__main__`` is a command line and may name its flags."""
    root = Path(__file__).resolve().parents[1] / package
    files = [p for p in sorted(root.rglob("*.py")) if p.name != "__main__.py"]
    assert len(files) > 10
    named = [f"{p.relative_to(root.parent)}:{line}: {text!r}" for p in files
             if TWO_DASHES_POSSIBLE.search(p.read_text()) for line, text in _message_strings(p) if FLAG.search(text)]
    assert not named, "messages that name a command-line flag (word it in cellctl/hints.py):\n" + "\n".join(named)


def test_the_flag_check_finds_a_flag() -> None:
    """The scan above sees f-string parts and plain strings, and leaves docstrings alone."""
    src = ('"""Uses --doc-flag."""\ndef f(x):\n    """--also-doc"""\n    raise ValueError(f"lower --dpi, got {x}")\n'
           'HINT = "use the other --setup"\n')
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "m.py"
        p.write_text(src)
        found = [text for _, text in _message_strings(p) if FLAG.search(text)]
    assert sorted(found) == ["lower --dpi, got ", "use the other --setup"]
    assert not FLAG.search("x--y") and not FLAG.search("a -- b") and FLAG.search("give (--T-base-target)")
    for flagged in ('"lower --dpi"', '"lower -" "-dpi"', "'lower -'\n    '-dpi'", '"lower \\x2d-dpi"'):
        assert TWO_DASHES_POSSIBLE.search(flagged), flagged  # the modules the scan reads include these


def test_front_ends_word_the_way_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 4-DOF refusal names the 6-DOF solver in the library's words (``alternative``); the CLI says to
    leave out its --dof 4, the capture routine to run with dof 6; the print's dpi is --dpi on the CLI."""
    from calibration.camera_model import CameraModel
    from calibration.handeye import HandEyeError, calibrate_handeye_dof4
    from calibration.io import read_poses_csv
    from calibration.observations import Detection
    from calibration.synthetic import write_example
    from calibration.targets import load_target
    from cellctl.cli import main
    from cellctl.hints import CLI, ROUTINE, handeye_message

    d = write_example("scara", str(tmp_path / "scara"))
    rows = Path(d["poses.csv"]).read_text().splitlines()
    name, *values = rows[4].split(",")
    values[3] = str(float(values[3]) + 0.1)  # station 3 tilted by about 5 deg: no longer a turn about base z
    rows[4] = ",".join([name, *values])
    Path(d["poses.csv"]).write_text("\n".join(rows) + "\n")
    args = ["calib", "handeye", "--setup", "eye-in-hand", "--camera", d["cam.json"], "--target", d["board.yaml"],
            "--dataset", str(tmp_path / "scara"), "--detections", d["detections.json"], "--dof", "4"]
    assert main([*args, "--target-z-mm", "12"]) == 2
    err = capsys.readouterr().err
    assert "tilted" in err and "leave out --dof 4" in err and err.count("\n") == 1, err
    assert main([*args, "--target-z-mm", "nan"]) == 2
    assert "--target-z-mm must be a finite height" in capsys.readouterr().err

    poses = read_poses_csv(d["poses.csv"])
    camera = CameraModel.from_dict(json.loads(Path(d["cam.json"]).read_text()))
    detections = [Detection.from_json(x) for x in json.loads(Path(d["detections.json"]).read_text())]
    with pytest.raises(HandEyeError) as refused:
        calibrate_handeye_dof4("eye-in-hand", poses.T_base_tool, detections, camera, load_target(d["board.yaml"]),
                               12.0)
    assert refused.value.alternative == "dof6" and not FLAG.search(str(refused.value))
    routine = handeye_message(refused.value, ROUTINE)
    assert routine.startswith(str(refused.value)) and "dof 6" in routine and not FLAG.search(routine)
    assert "leave out --dof 4" in handeye_message(refused.value, CLI)

    board = tmp_path / "board.yaml"
    board.write_text("type: chessboard\ncols: 9\nrows: 6\nsquare_mm: 25\n")
    assert main(["target", "render", "--target", str(board), "--out", str(tmp_path / "b.png"), "--dpi", "5"]) == 2
    err = capsys.readouterr().err
    assert "dpi must be between 10 and 2400" in err and "check --dpi" in err and err.count("\n") == 1, err


def test_no_assert_in_the_service_or_the_drivers() -> None:
    """``python -O`` drops asserts: a check the product relies on is a typed error instead."""
    root = Path(__file__).resolve().parents[1]
    texts = {path: path.read_text() for package in ("cellctl", "drivers")
             for path in sorted((root / package).rglob("*.py"))}
    assert len(texts) > 100
    found = [f"{path.relative_to(root)}:{node.lineno}" for path, text in texts.items()
             if "assert" in text  # (an assert statement is spelled out: a module without the word has none)
             for node in ast.walk(ast.parse(text, str(path))) if isinstance(node, ast.Assert)]
    assert not found, f"replace these asserts with typed checks: {found}"
