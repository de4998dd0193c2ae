"""One error root per library: every exception class of ``calibration`` and ``vision`` derives from it.

The REST API maps these roots (and the drivers' ``DriverError``) to a 4xx; any other exception is
a bug (a 500 with a request id). A new error class outside its root would silently become a 500.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

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
